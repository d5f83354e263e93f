"""The CLI end to end, in a temporary folder: files written, every backend present, compare."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from bench.results import COLUMNS, read_results
from impls import registry
from tests.conftest import BACKEND_IDS

ROOT = Path(__file__).resolve().parent.parent


def bench(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "bench", *args], cwd=cwd or ROOT, capture_output=True, text=True, timeout=900)


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("run") / "quick"
    p = bench("run", "--suite", "quick", "--out", str(out), "--min-time", "0.02", "--min-repeats", "3", "--no-progress",
              "--no-claims")
    assert p.returncode == 0, p.stdout + p.stderr
    return out


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


def test_every_available_backend_appears(quick_run):
    df = read_results(quick_run)
    available = [b for b in BACKEND_IDS if not isinstance(registry.resolve(b), registry.Unavailable)]
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


def test_results_are_never_overwritten(quick_run):
    p = bench("run", "--suite", "quick", "--out", str(quick_run), "--no-progress", "--backend", "numpy")
    assert p.returncode == 2 and "never overwritten" in p.stdout


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
    assert p.returncode != 0 and "unknown suite" in (p.stdout + p.stderr)
    p = bench("run", "--case", "nosuch.*", "--out", str(tmp_path / "y"), "--no-progress")
    assert p.returncode == 2 and "no case matches" in p.stdout


def test_committed_baseline_has_no_accuracy_regression(quick_run):
    """What CI gates on: the quick run against reports/baseline (regenerate it with
    `python -m bench baseline` when an accuracy change is intended)."""
    p = bench("compare", str(ROOT / "reports" / "baseline"), str(quick_run))
    assert p.returncode == 0, p.stdout + p.stderr
    # and it compares every row: a knob added or renamed changes the rows' keys, and rows on one
    # side only ("missing"/"new") never fail a comparison, so a stale baseline would gate nothing
    from bench.compare import compare

    verdicts = compare(read_results(ROOT / "reports" / "baseline"), read_results(quick_run), same_machine=False)
    unmatched = verdicts[verdicts["accuracy"].isin(["missing", "new"])]
    assert unmatched.empty, f"regenerate the baseline (python -m bench baseline): {len(unmatched)} unmatched rows"


def test_plugged_in_and_broken_backends_are_rows_not_crashes(tmp_path):
    out = tmp_path / "plug"
    p = bench("run", "--suite", "quick", "--accuracy-only", "--no-claims", "--no-progress", "--out", str(out),
              "--backend", "numpy,tests.test_bench_fakes:FakeBackend,nosuch.module:Backend")
    assert p.returncode == 0, p.stdout + p.stderr
    df = read_results(out)
    reasons = df.groupby("backend")["reason"].first().to_dict()
    assert "does not implement sphere_trace" in reasons["tests.test_bench_fakes:FakeBackend"]
    assert "backend unavailable" in reasons["nosuch.module:Backend"] and "nosuch" in reasons["nosuch.module:Backend"]
    numpy_rows = df[df["backend"] == "numpy"]
    assert "failed" not in set(numpy_rows["outcome"]) and (numpy_rows["outcome"] == "ok").any()
    assert numpy_rows.loc[numpy_rows["outcome"] == "skipped", "reason"].str.len().gt(0).all()
    assert "does not implement sphere_trace" in (out / "report.html").read_text()


def test_compare_missing_run_is_a_clear_error(tmp_path):
    p = bench("compare", str(tmp_path / "nope"), str(tmp_path / "nope2"))
    assert p.returncode == 2 and "no results at" in p.stdout


def test_cases_lists_the_catalog():
    p = bench("cases")
    assert p.returncode == 0 and "sphere.camera.64x64" in p.stdout


def test_speed_command_reports_ratios_errors_and_false_answers(tmp_path, capsys):
    import json

    from bench.cli import main

    out = tmp_path / "speed.json"
    assert main(["speed", "--backend", "numpy", "--side", "16", "--repeats", "1", "--out", str(out)]) == 0
    rows = json.loads(out.read_text())
    assert {r["scene"] for r in rows} == {"sphere", "torus∪box"}
    for r in rows:
        assert r["rays"] == 256 and r["x_unit"] > 0 and r["false_hits"] == 0 and r["false_misses"] == 0
        assert r["err_max"] < 1e-9
    assert "x_unit" in capsys.readouterr().out
    assert all(r["allocator"] != "" for r in rows)
    assert main(["speed", "--backend", "numpy", "--side", "8", "--repeats", "1", "--allocator", "default",
                 "--out", str(out)]) == 0
    assert {r["allocator"] for r in json.loads(out.read_text())} == {"default"}
    assert "allocator: default" in capsys.readouterr().out


def test_speed_unit_is_the_exact_sphere_hit_with_or_without_buffers():
    from bench.speed import lean_sphere_hits, unit_timer
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
