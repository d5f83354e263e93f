"""``--resume`` finishes a run that was killed: tested by killing a real run."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from bench.run.results import read_results
from tests.conftest import HANG_GUARD_S

ROOT = Path(__file__).resolve().parent.parent
KEY = ["case_id", "backend", "dtype", "method", "knob", "quantity"]


@pytest.mark.slow
def test_killed_run_is_finished_by_resume(tmp_path):
    """A quick-suite run killed after its first rows reached disk, then resumed.  Its plan is the
    quick suite's for three methods (two families, 24 configurations, each timed for at least
    1 s before the kill): enough rows on both sides of the kill, without re-timing the catalog."""
    out = tmp_path / "run"
    methods = ["sphere_trace", "hybrid_secant", "normal"]
    args = [sys.executable, "-m", "bench", "run", "--suite", "quick", "--backend", "numpy", "--out", str(out),
            "--method", ",".join(methods), "--no-progress", "--no-claims"]
    p = subprocess.Popen(args + ["--min-time", "1.0", "--min-repeats", "3"], cwd=ROOT, stdout=subprocess.DEVNULL,
                         stderr=subprocess.PIPE)
    deadline = time.monotonic() + HANG_GUARD_S
    while not (out / "results.parquet").exists() and time.monotonic() < deadline and p.poll() is None:
        time.sleep(0.05)
    p.send_signal(signal.SIGKILL)
    p.wait(timeout=30)
    assert p.returncode == -signal.SIGKILL, "the run finished before it could be killed; slow it down"
    partial = read_results(out)
    env = json.loads((out / "environment.json").read_text())
    assert env["complete"] == "false" and len(partial) > 0

    q = subprocess.run(args[:-1] + ["--resume", "--min-time", "0.01", "--min-repeats", "3"], cwd=ROOT,
                       capture_output=True, text=True, timeout=HANG_GUARD_S)
    assert q.returncode == 0, q.stdout + q.stderr
    full = read_results(out)
    env2 = json.loads((out / "environment.json").read_text())
    assert env2["complete"] == "true" and env2["resumed"] == "1" and env2["run_id"] == env["run_id"]
    assert len(full) > len(partial)
    assert not full.duplicated(KEY).any()
    assert set(full["run_id"]) == {env["run_id"]}
    # the rows finished before the kill are kept as they were (not re-measured)
    merged = partial.merge(full, on=KEY, suffixes=("_a", "_b"))
    assert len(merged) == len(partial)
    assert (merged["time_samples_s_a"] == merged["time_samples_s_b"]).all()
    # and the resumed run has exactly the rows of an uninterrupted plan
    from bench.run import runner
    from bench.run.suites import get_suite

    plan = runner.plan(get_suite("quick"), ["numpy"], None, methods, None)
    assert {tuple(map(str, c.key)) for c in plan} == set(map(tuple, full[runner.CONFIG_KEY].astype(str).itertuples(
        index=False, name=None)))
    assert (out / "report.html").exists()


@pytest.mark.slow  # compiles many kernels or sweeps a whole catalog
def test_resume_finishes_the_plan_the_run_started_not_the_suite_default(tmp_path):
    """``--resume`` restores the recorded ``--case``/``--method``/``--backend``: typing the hint the
    run prints (``--resume --out DIR``) finishes a ``--case`` sweep, not the suite's default cases;
    an option given on resume that contradicts the recorded one is an error naming it."""
    from bench.run import runner
    from bench.run.suites import get_suite

    out = tmp_path / "run"
    base = [sys.executable, "-m", "bench", "run", "--out", str(out), "--no-progress", "--no-claims"]
    first = subprocess.run(base + ["--backend", "numpy", "--case", "box.inside,cylinder.parallel", "--method",
                                   "march_bisect,normal", "--accuracy-only", "--budget", "0.001"],
                           cwd=ROOT, capture_output=True, text=True, timeout=HANG_GUARD_S)
    assert first.returncode == 1 and "INCOMPLETE" in first.stderr, first.stdout + first.stderr
    recorded = json.loads(json.loads((out / "environment.json").read_text())["run_options"])
    assert recorded["case"] == "box.inside,cylinder.parallel" and recorded["backend"] == ["numpy"]

    again = subprocess.run(base + ["--resume"], cwd=ROOT, capture_output=True, text=True, timeout=HANG_GUARD_S)
    assert again.returncode == 0, again.stdout + again.stderr
    full = read_results(out)
    plan = runner.plan(get_suite("quick"), ["numpy"], "box.inside,cylinder.parallel", ["march_bisect", "normal"], None)
    assert {tuple(map(str, c.key)) for c in plan} == set(map(tuple, full[runner.CONFIG_KEY].astype(str).itertuples(
        index=False, name=None)))
    assert (full["n_samples"].fillna(0) == 0).all()  # --accuracy-only was restored too: no timing samples

    clash = subprocess.run(base + ["--resume", "--case", "box.*"], cwd=ROOT, capture_output=True, text=True,
                           timeout=HANG_GUARD_S)
    assert clash.returncode == 2 and "--case: the run in" in clash.stderr and "'box.inside,cylinder.parallel'" in \
        clash.stderr, clash.stderr
    same = subprocess.run(base + ["--resume", "--backend", "numpy", "--method", "march_bisect", "--method", "normal"],
                          cwd=ROOT, capture_output=True, text=True, timeout=HANG_GUARD_S)
    assert same.returncode == 0 and "error:" not in same.stderr, same.stderr  # the recorded options, retyped
    narrower = subprocess.run(base + ["--resume", "--dtype", "float64"], cwd=ROOT, capture_output=True, text=True,
                              timeout=HANG_GUARD_S)
    assert narrower.returncode == 2 and "--dtype: the run in" in narrower.stderr, narrower.stderr
