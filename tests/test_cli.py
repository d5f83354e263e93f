"""The CLI end to end, in a temporary folder: files written, every backend present, compare."""

from __future__ import annotations

import json
import re
import shutil
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from bench.run.results import COLUMNS, read_results
from impls import registry
from tests.conftest import BACKEND_IDS, bench_cli

ROOT = Path(__file__).resolve().parent.parent


def bench(*args, cwd=None):
    return bench_cli(*args, cwd=cwd)


@pytest.mark.slow
def test_the_quick_run_covers_its_whole_plan_and_shows_progress_when_piped(quick_run_and_stdout):
    """No wall-clock budget cuts the plan, whatever the machine's load; progress lines come with
    counts and elapsed time although stdout is a pipe; the closing output is short."""
    from bench.run import runner
    from bench.run.suites import get_suite

    quick_run, out = quick_run_and_stdout
    env = json.loads((quick_run / "environment.json").read_text())
    assert env["complete"] == "true" and env["budget_s"] == "none"
    df = read_results(quick_run)
    assert not df["reason"].fillna("").str.startswith("over the run's time budget").any()
    from bench.commands._common import resolve_backends

    ids = list(resolve_backends(registry.default_ids(), 1)[0])  # keyed by id, as the run names them (warp:cpu)
    plan = runner.plan(get_suite("quick"), ids, None, None, None)
    assert {tuple(map(str, c.key)) for c in plan} == set(map(tuple, df[runner.CONFIG_KEY].astype(str).itertuples(
        index=False, name=None)))
    lines = out.splitlines()
    assert any(re.search(r"\[ *\d+\.\d s\] plan: \d+ configurations", ln) for ln in lines), out[:2000]
    progress = [ln for ln in lines if re.search(r"configurations \d+/\d+ \(\d+%\): \d+ ok, \d+ skipped, \d+ failed", ln)]
    assert len(progress) >= 5, out[:3000]
    assert any("report: writing" in ln for ln in lines)
    assert f"report: {quick_run / 'report.html'}" in out
    assert max(map(len, lines)) < 250, "progress and closing lines are one screen wide"
    # the closing output (after the report is written) is a summary, not the table; progress
    # lines before it grow with the run's length
    closing = lines[max(i for i, ln in enumerate(lines) if "report: writing" in ln) + 1:]
    assert 0 < len(closing) < 40, "the closing output is a summary, not the table:\n" + "\n".join(closing)


@pytest.mark.slow
def test_run_writes_every_file(quick_run):
    for name in ("results.parquet", "results.csv", "report.md", "report.html", "environment.json"):
        assert (quick_run / name).stat().st_size > 0, name
    df = read_results(quick_run)
    assert set(COLUMNS) <= set(df.columns)
    csv = pd.read_csv(quick_run / "results.csv")
    assert len(csv) == len(df)
    env = json.loads((quick_run / "environment.json").read_text())
    assert env["version.numpy"] and env["commit"] and env["cpu_count"]
    import platform

    if platform.system() == "Linux" and platform.libc_ver()[0] == "glibc":  # the default --allocator tuned
        assert env["allocator"].startswith("glibc mallopt M_MMAP_THRESHOLD=1GiB")
    else:
        assert env["allocator"] == "default"


@pytest.mark.slow
def test_every_available_backend_appears(quick_run):
    df = read_results(quick_run)
    # (a run names a backend by its id, which may differ from the entry point's name: warp is warp:cpu)
    available = [r.id for r in map(registry.resolve, BACKEND_IDS) if not isinstance(r, registry.Unavailable)]
    ran = set(df.loc[df["outcome"] == "ok", "backend"])
    assert set(available) <= ran
    html = (quick_run / "report.html").read_text()
    for b in available:
        assert b in html
    assert "data:image/png;base64," in html
    for section in ("Best accuracy per backend", "Fastest configuration reaching an error target", "Time versus error",
                    "Convergence", "Support matrix", "Environment"):
        assert section in html, section
        assert section in (quick_run / "report.md").read_text(), section
    # every configuration appears: one row per (configuration, quantity), no duplicates
    assert not df.duplicated(["case_id", "backend", "dtype", "method", "knob", "quantity"]).any()
    assert "<script" not in html and "http://" not in html and "https://" not in html  # offline


@pytest.mark.slow
def test_results_are_never_overwritten(quick_run, tmp_path):
    p = bench("run", "--suite", "quick", "--out", str(quick_run), "--no-progress", "--backend", "numpy")
    assert p.returncode == 2 and "never overwritten" in p.stderr and "--out" in p.stderr
    # a folder with results.csv and environment.json but no parquet (the committed baseline's shape)
    base = tmp_path / "baseline"
    shutil.copytree(ROOT / "reports" / "baseline", base)
    before = {f.name: f.read_bytes() for f in base.iterdir()}
    p = bench("run", "--suite", "quick", "--out", str(base), "--no-progress", "--backend", "numpy",
              "--case", "sphere.camera.64x64", "--method", "sphere_trace")
    assert p.returncode == 2 and "never overwritten" in p.stderr, p.stdout + p.stderr
    assert {f.name: f.read_bytes() for f in base.iterdir()} == before
    claims_only = tmp_path / "claims"
    claims_only.mkdir()
    (claims_only / "claims.csv").write_text("id\n")
    p = bench("run", "--out", str(claims_only), "--no-progress", "--backend", "numpy")
    assert p.returncode == 2 and "claims.csv" in p.stderr
    p = bench("run", "--out", str(base / "results.csv"), "--no-progress", "--backend", "numpy")
    assert p.returncode == 2 and "--out" in p.stderr


@pytest.mark.slow
def test_compare_same_run_passes_and_planted_regression_fails(quick_run, tmp_path):
    p = bench("compare", str(quick_run), str(quick_run))
    assert p.returncode == 0, p.stdout + p.stderr
    bad = tmp_path / "bad"
    shutil.copytree(quick_run, bad)
    df = read_results(bad)
    i = df.index[(df["outcome"] == "ok") & np.isfinite(df["error_max"])][0]
    df.loc[i, "error_max"] = df.loc[i, "error_max"] * 10 + 1e-6
    (bad / "results.parquet").unlink()
    df.to_csv(bad / "results.csv", index=False)
    p = bench("compare", str(quick_run), str(bad))
    assert p.returncode == 1, p.stdout + p.stderr
    assert "regression" in p.stdout


def test_bad_arguments_get_clear_errors(tmp_path):
    p = bench("run", "--suite", "nosuch", "--out", str(tmp_path / "x"))
    assert p.returncode == 2 and "unknown suite" in p.stderr
    p = bench("run", "--case", "nosuch.*", "--out", str(tmp_path / "y"), "--no-progress")
    assert p.returncode == 2 and "no case matches" in p.stderr


@pytest.mark.slow
def test_committed_baseline_has_no_accuracy_regression(quick_run):
    """What CI gates on: the quick run against reports/baseline (regenerate it with
    `python -m bench baseline` when an accuracy change is intended)."""
    p = bench("compare", str(ROOT / "reports" / "baseline"), str(quick_run))
    assert p.returncode == 0, p.stdout + p.stderr
    # and it compares every row: a knob added or renamed changes the rows' keys, and rows on one
    # side only ("missing"/"new") never fail a comparison, so a stale baseline would gate nothing
    from bench.report.compare import compare

    verdicts = compare(read_results(ROOT / "reports" / "baseline"), read_results(quick_run), same_machine=False)
    unmatched = verdicts[verdicts["accuracy"].isin(["missing", "new"])]
    assert unmatched.empty, f"regenerate the baseline (python -m bench baseline): {len(unmatched)} unmatched rows"


@pytest.mark.slow
def test_plugged_in_and_broken_backends_are_rows_not_crashes(tmp_path):
    """The quick suite's plan (and its stability and report stages) on numpy beside a plug-in
    that loads, one that does not and one that returns a bad status.  The plan is the quick
    suite's for three methods: the two the faulty plug-ins offer (sphere_trace, hybrid_secant)
    and one of another family (normal, fed by the root finder's hits): every row the faults
    could touch, without timing the whole catalog's numpy rows twice over."""
    out = tmp_path / "plug"
    broken = "tests.test_bench_fakes:BrokenFactoryBackend"
    bad_status = "tests.test_bench_fakes:BadStatusBackend"
    methods = ["sphere_trace", "hybrid_secant", "normal"]
    p = bench("run", "--suite", "quick", "--accuracy-only", "--no-claims", "--no-progress", "--out", str(out),
              "--method", ",".join(methods),
              "--backend", f"numpy,tests.test_bench_fakes:FakeBackend,{broken},{bad_status}")
    assert p.returncode == 0, p.stdout + p.stderr
    assert "Traceback" not in p.stdout + p.stderr
    df = read_results(out)
    reasons = df.groupby("backend")["reason"].first().to_dict()
    # a plug-in that loads is named by its own id (FakeBackend's "fake"), one that does not by its spec
    assert "tests.test_bench_fakes:FakeBackend" not in reasons and bad_status not in reasons
    assert "does not implement sphere_trace" in reasons["fake"]
    assert "backend unavailable" in reasons[broken] and "planted" in reasons[broken]
    bad = df[(df["backend"] == "BadStatusBackend") & (df["outcome"] == "failed")]
    assert len(bad) and bad["reason"].str.contains("[7]", regex=False).all()
    from bench.run import runner
    from bench.run.suites import get_suite

    plan = runner.plan(get_suite("quick"), ["numpy"], None, methods, None)
    np_keys = set(map(tuple, df.loc[df["backend"] == "numpy", runner.CONFIG_KEY].astype(str).itertuples(
        index=False, name=None)))
    assert np_keys == {tuple(map(str, c.key)) for c in plan}  # no numpy row lost
    numpy_rows = df[df["backend"] == "numpy"]
    assert "failed" not in set(numpy_rows["outcome"]) and (numpy_rows["outcome"] == "ok").any()
    assert numpy_rows.loc[numpy_rows["outcome"] == "skipped", "reason"].str.len().gt(0).all()
    assert "does not implement sphere_trace" in (out / "report.html").read_text()


def test_compare_missing_run_is_a_clear_error(tmp_path):
    p = bench("compare", str(tmp_path / "nope"), str(tmp_path / "nope2"))
    assert p.returncode == 2 and "no results at" in p.stderr


def test_cases_lists_the_catalog():
    p = bench("cases")
    assert p.returncode == 0 and "sphere.camera.64x64" in p.stdout


def test_speed_command_reports_ratios_errors_and_false_answers(tmp_path, capsys):
    import json

    from bench.commands import main

    out = tmp_path / "speed.json"
    assert main(["speed", "--backend", "numpy", "--side", "16", "--repeats", "1", "--out", str(out)]) == 0
    rows = json.loads(out.read_text())
    assert {r["scene"] for r in rows} == {"sphere", "torus∪box"}
    assert {r["backend"] for r in rows} >= {"numpy", "peer:scipy"}  # the peers' rows, beside the backends'
    for r in rows:
        assert r["rays"] == 256 and r["x_unit"] > 0 and r["false_hits"] == 0 and r["false_misses"] == 0
        # the numba per-ray tracer stops at φ < 1e-9: its depth error is that over |cos| at grazing hits
        assert r["err_max"] < (1e-6 if r["backend"] == "peer:numba-st" else 1e-9)
        assert r["evals_mean"] > 0
    assert "x_unit" in capsys.readouterr().out
    assert all(r["allocator"] != "" for r in rows)
    assert main(["speed", "--backend", "numpy", "--side", "8", "--repeats", "1", "--allocator", "default",
                 "--no-peers", "--out", str(out)]) == 0
    assert {r["backend"] for r in json.loads(out.read_text())} == {"numpy"}
    assert {r["allocator"] for r in json.loads(out.read_text())} == {"default"}
    assert "allocator: default" in capsys.readouterr().out


def test_speed_unit_is_the_exact_sphere_hit_with_or_without_buffers():
    from bench.studies.speed import lean_sphere_hits, unit_timer
    from reference import Sphere

    rng = np.random.default_rng(7)
    o = rng.normal(size=(500, 3)) * 2
    d = rng.normal(size=(500, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    exact = Sphere().first_hit(o, d, -np.inf)  # every crossing, behind the origin too
    for t in (lean_sphere_hits(o, d), lean_sphere_hits(o, d, np.empty(500), (np.empty(500), np.empty(500)))):
        assert np.array_equal(np.isinf(t), np.isinf(exact))
        np.testing.assert_allclose(t[np.isfinite(t)], exact[np.isfinite(exact)], rtol=0, atol=1e-12)
    unit_timer(o, d)()  # runs on its own buffers


def _truncated_baseline(tmp_path):
    d = tmp_path / "half"
    d.mkdir()
    lines = (ROOT / "reports" / "baseline" / "results.csv").read_text().splitlines(keepends=True)
    (d / "results.csv").write_text("".join(lines[: len(lines) // 2]))
    shutil.copyfile(ROOT / "reports" / "baseline" / "environment.json", d / "environment.json")
    return d


def _incomplete_copy(tmp_path):
    d = tmp_path / "incomplete"
    shutil.copytree(ROOT / "reports" / "baseline", d)
    env = json.loads((d / "environment.json").read_text())
    env.update(complete="false", incomplete_reason="over the run's time budget (planted)")
    (d / "environment.json").write_text(json.dumps(env))
    return d


def _corrupt_run(tmp_path):
    d = tmp_path / "corrupt"
    d.mkdir()
    (d / "environment.json").write_text("{}")
    (d / "results.parquet").write_bytes(b"PAR1 this is not a parquet file")
    return d


def _garbage_csv(tmp_path):
    (tmp_path / "garbage.csv").write_text("x,y\n1,2\n")
    return tmp_path / "garbage.csv"


def _all_versions_changed(tmp_path):
    """The baseline with every case_version changed and every error raised to 10: nothing is
    comparable (issue 33, finding 1)."""
    d = tmp_path / "changed"
    shutil.copytree(ROOT / "reports" / "baseline", d)
    df = pd.read_csv(d / "results.csv")
    df["case_version"] = "0123456789ab"
    df["error_max"] = 10.0
    df.to_csv(d / "results.csv", index=False)
    return d


def _baseline_copy(tmp_path):
    shutil.copytree(ROOT / "reports" / "baseline", tmp_path / "b")
    return tmp_path / "b"


BASELINE = str(ROOT / "reports" / "baseline")
ONE = ["--case", "sphere.camera.64x64", "--method", "sphere_trace", "--no-claims", "--accuracy-only"]

# (argv from tmp_path, exit code, what stderr must name)
USER_ERRORS = {
    "run --threads 0": (lambda t: ["run", "--threads", "0"], 2, "--threads"),
    "run --budget -1": (lambda t: ["run", "--budget", "-1"], 2, "--budget"),
    "run --timeout nan": (lambda t: ["run", "--timeout", "nan"], 2, "--timeout"),
    "run --backend nosuch": (lambda t: ["run", "--backend", "nosuch", "--out", str(t / "o")], 2, "--backend"),
    "run plug-in spec, undotted module": (lambda t: ["run", "--backend", "nosuchmodule:Backend", "--out", str(t / "o")],
                                          2, "--backend"),
    "run plug-in spec, no such attribute": (lambda t: ["run", "--backend", "tests.test_bench_fakes:Nope", "--out",
                                                       str(t / "o")], 2, "--backend"),
    "run --out a baseline": (lambda t: ["run", "--out", str(_baseline_copy(t)), "--backend", "numpy"], 2, "--out"),
    "run where every configuration failed": (
        lambda t: ["run", "--backend", "tests.test_bench_fakes:BadStatusBackend", "--out", str(t / "o"), *ONE], 1,
        "no configuration ran"),
    "run that spends its --budget": (
        lambda t: ["run", "--backend", "numpy,tests.test_bench_fakes:SleepyBackend", "--budget", "2", "--out",
                   str(t / "o"), *ONE], 1, "INCOMPLETE"),
    # issue 33, finding 8: contradictory or empty options are refused, naming them
    "run --min-time 10 --max-time 1": (lambda t: ["run", "--min-time", "10", "--max-time", "1", "--out",
                                                  str(t / "o"), *ONE], 2, "--min-time 10 and --max-time 1"),
    "run --max-time below the suite's --min-time": (lambda t: ["run", "--max-time", "0.01", "--out", str(t / "o"),
                                                               "--case", "sphere.camera.64x64"], 2, "--max-time"),
    "run --method ''": (lambda t: ["run", "--method", "", "--out", str(t / "o")], 2, "--method"),
    "run --backend ','": (lambda t: ["run", "--backend", ",", "--out", str(t / "o")], 2, "--backend"),
    "run --case ''": (lambda t: ["run", "--case", "", "--out", str(t / "o")], 2, "--case"),
    "run --dtype ''": (lambda t: ["run", "--dtype", "", "--out", str(t / "o")], 2, "--dtype"),
    "run --rounds 3 --accuracy-only": (lambda t: ["run", "--rounds", "3", "--out", str(t / "o"), *ONE], 2,
                                       "--rounds 3 and --accuracy-only"),
    "run --rerun-case without --resume": (lambda t: ["run", "--rerun-case", "user.*", "--out", str(t / "o")], 2,
                                          "--rerun-case"),
    "report on a missing directory": (lambda t: ["report", str(t / "nope")], 2, "RUN_DIR"),
    "report on a corrupt parquet": (lambda t: ["report", str(_corrupt_run(t))], 2, "RUN_DIR"),
    "compare with a garbage results.csv": (lambda t: ["compare", BASELINE, str(_garbage_csv(t))], 2, "BASE/NEW"),
    "compare against a truncated results file": (lambda t: ["compare", BASELINE, str(_truncated_baseline(t))], 1,
                                                 "missing in NEW"),
    "compare against an incomplete run": (lambda t: ["compare", BASELINE, str(_incomplete_copy(t))], 1,
                                          "NEW is an incomplete run"),
    "compare where no row is comparable": (lambda t: ["compare", BASELINE, str(_all_versions_changed(t))], 1,
                                           "were comparable"),
    "compare --min-comparable 0": (lambda t: ["compare", BASELINE, BASELINE, "--min-comparable", "0"], 2,
                                   "--min-comparable"),
    "speed --side 0": (lambda t: ["speed", "--side", "0"], 2, "--side"),
    "speed --knobs '{bad json'": (lambda t: ["speed", "--knobs", "{bad json"], 2, "--knobs"),
    "speed --backend nosuch": (lambda t: ["speed", "--backend", "nosuch", "--side", "4"], 2, "--backend"),
    "speed --method nosuch": (lambda t: ["speed", "--method", "nosuch", "--side", "4"], 2, "--method"),
    "cases --tag nosuch": (lambda t: ["cases", "--tag", "nosuch"], 2, "--tag"),
    "sampling --targets x": (lambda t: ["sampling", "--targets", "x"], 2, "--targets"),
    "sampling --case nosuch": (lambda t: ["sampling", "--case", "nosuch"], 2, "--case"),
}


#: the quick tier's (``-m "not slow"``) share of :data:`USER_ERRORS`: one error of each command's
#: own parsing and one of a run's plan; the others (0.6 s of two interpreters each, 19 s for the 31
#: on 2 cores) run in the whole suite, CI's gate
USER_ERRORS_QUICK = ("run --threads 0", "run --backend nosuch", "run where every configuration failed",
                     "report on a missing directory", "compare with a garbage results.csv", "speed --side 0",
                     "cases --tag nosuch")


@pytest.mark.parametrize("name", [n if n in USER_ERRORS_QUICK else pytest.param(n, marks=pytest.mark.slow)
                                  for n in USER_ERRORS])
def test_user_errors_end_in_one_clear_line_and_a_nonzero_exit(name, tmp_path):
    argv, code, names = USER_ERRORS[name]
    p = bench(*argv(tmp_path))
    assert p.returncode == code, (p.returncode, p.stdout[-2000:], p.stderr[-2000:])
    assert "Traceback" not in p.stderr + p.stdout, p.stderr
    assert names in p.stderr, p.stderr
    assert re.search(r"(^|: )error: ", p.stderr, re.M), p.stderr
    if name == "run that spends its --budget":  # the budget interrupted the call in flight (a 30 s sleep)
        from bench.run.results import OVER_BUDGET

        # rows name the plug-in by its id (SleepyBackend), not by its spec
        sleepy = read_results(tmp_path / "o").query("backend == 'SleepyBackend'")
        assert len(sleepy), "no row of the plug-in"
        assert sleepy["reason"].str.startswith(OVER_BUDGET).all(), sleepy["reason"].tolist()
        assert sleepy["reason"].str.contains("interrupted in flight").any(), sleepy["reason"].tolist()


def test_the_quick_tiers_user_errors_are_listed_ones():
    assert set(USER_ERRORS_QUICK) <= set(USER_ERRORS), set(USER_ERRORS_QUICK) - set(USER_ERRORS)


def test_compare_may_allow_a_partial_selection_on_purpose(tmp_path):
    p = bench("compare", BASELINE, str(_truncated_baseline(tmp_path)), "--allow-missing")
    assert p.returncode == 0, p.stdout + p.stderr
