"""``--resume`` finishes a run that was killed: tested by killing a real run."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

from bench.results import read_results

ROOT = Path(__file__).resolve().parent.parent
KEY = ["case_id", "backend", "dtype", "method", "knob", "quantity"]


def test_killed_run_is_finished_by_resume(tmp_path):
    out = tmp_path / "run"
    args = [sys.executable, "-m", "bench", "run", "--suite", "quick", "--backend", "numpy", "--out", str(out),
            "--no-progress", "--no-claims"]
    p = subprocess.Popen(args + ["--min-time", "1.0", "--min-repeats", "3"], cwd=ROOT, stdout=subprocess.DEVNULL,
                         stderr=subprocess.PIPE)
    deadline = time.monotonic() + 60
    while not (out / "results.parquet").exists() and time.monotonic() < deadline and p.poll() is None:
        time.sleep(0.05)
    p.send_signal(signal.SIGKILL)
    p.wait(timeout=30)
    assert p.returncode == -signal.SIGKILL, "the run finished before it could be killed; slow it down"
    partial = read_results(out)
    env = json.loads((out / "environment.json").read_text())
    assert env["complete"] == "false" and len(partial) > 0

    q = subprocess.run(args[:-1] + ["--resume", "--min-time", "0.01", "--min-repeats", "3"], cwd=ROOT,
                       capture_output=True, text=True, timeout=300)
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
    from bench import runner
    from bench.suites import get_suite

    plan = runner.plan(get_suite("quick"), ["numpy"], None, None, None)
    assert {tuple(map(str, c.key)) for c in plan} == set(map(tuple, full[runner.CONFIG_KEY].astype(str).itertuples(
        index=False, name=None)))
    assert (out / "report.html").exists()
