"""A backend that kills its process (a segfault, an abort, an ``os._exit`` in a native library)
costs its own configuration and no other row: ``python -m bench run`` supervises the process that
runs it and resumes the run past the configuration that killed it (bench/run/supervise.py,
``runner.INFLIGHT``); the side stages' process is started again past it the same way
(bench/commands/_side_stages.py).  The crashing backend is tests/crash_backend.py."""

from __future__ import annotations

import json
import textwrap
import os

import pandas as pd
import pytest

from bench.run import supervise
from bench.run.runner import CRASHED, INFLIGHT
from tests.conftest import bench_cli

#: each test starts several interpreters (one more per crash)
pytestmark = pytest.mark.slow

CRASHY = "tests.crash_backend:CrashBackend"
#: the run's own configurations only: the stability stage (a second process, its own test below)
#: and the claims took 22 of a crash test's 28 s
QUIET = ("--no-stability", "--no-claims", "--no-progress")
#: the hang tests' ``--timeout`` and hang threshold (``supervise.HUNG_AFTER_ENV``: killed at 1 × the
#: limit + 2 s = 7 s), sized to the work: their runs are accuracy-only (:data:`HANG_RUN`), one call
#: per configuration, 60–90 ms each for the other configurations here (numpy's sphere tracing on
#: the 32² torus camera, idle), so a limit of 5 s holds them on a machine 55× slower than an idle
#: one, and the hang costs 7 s of waiting (at 10 s and 1 × the limit + 5 s with timed runs of
#: ~0.2 s per configuration: 15 s of the command's wall time, twice, on a core doing nothing)
LIMIT, HUNG_AFTER = "5", "1,2"
HANG_RUN = ("--case", "torus.camera.32x32", "--method", "sphere_trace", "--accuracy-only", "--timeout", LIMIT)


def _configs(path) -> pd.DataFrame:
    return pd.read_csv(path).drop_duplicates(["case_id", "backend", "dtype", "method", "knob"])


@pytest.mark.parametrize("how", ["segv", "exit", "exit0"])
def test_a_backend_that_kills_its_process_costs_only_its_configuration(tmp_path, how):
    """Before: the run died with it (status 139), wrote no row, and ``--resume`` died again on the
    same configuration.  Now: that configuration is a failed row saying it crashed, every other
    configuration ran, the run is complete and says on stderr what happened.  ``exit0``: a backend's
    ``os._exit(0)`` ended the run with status 0, no results, no report and no word (its in-flight note
    left behind); it is a crash like any other exit inside a configuration."""
    out = tmp_path / "run"
    env = {**os.environ, "CRASH_METHOD": "sphere_trace", "CRASH_KNOB": "tol=1e-08", "CRASH_HOW": how}
    p = bench_cli("run", "--backend", f"{CRASHY},numpy", "--case", "torus.camera.32x32", "--method",
                  "sphere_trace,hybrid_secant", *QUIET, "--out", out, env=env)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    assert "the run's process died" in p.stderr and "sphere_trace" in p.stderr, p.stderr[-2000:]
    g = _configs(out / "results.csv")
    failed = g[g.outcome == "failed"]
    assert len(failed) == 1, failed[["backend", "method", "knob", "reason"]]
    row = failed.iloc[0]
    assert (row.backend, row.method) == ("crashy", "sphere_trace") and "tol=1e-08" in row.knob
    assert row.reason.startswith(CRASHED)
    # every other configuration ran, the crashing backend's other ones too, and as often as numpy's
    for bid in ("crashy", "numpy"):
        mine = g[g.backend == bid]
        assert (mine.outcome == "ok").sum() == (g[g.backend == "numpy"].outcome == "ok").sum() - (bid == "crashy")
    assert not (out / INFLIGHT).exists() and (out / "report.md").exists()
    env_rec = json.loads((out / "environment.json").read_text())
    assert env_rec["complete"] == "true" and int(env_rec["resumed"]) == 1


def test_the_side_stages_go_on_past_a_backend_that_kills_their_process(tmp_path):
    """The stability stage runs in a second process; a backend that killed it cost the stability
    stage and the claims of every backend.  Now the stages start again in a new process that
    resumes the stability stage past that configuration."""
    from bench.commands import parser
    from bench.commands._side_stages import SideStages
    from bench.report.tables import STABILITY_DIR

    args = parser().parse_args(["run", "--backend", f"{CRASHY},numpy", "--no-claims"])
    os.environ.update(CRASH_METHOD="sphere_trace", CRASH_KIND="torus", CRASH_DTYPE="float64", CRASH_HOW="exit")
    try:
        side = SideStages(("stability",), (args, str(tmp_path), "stability", False, False)).start()
        try:
            notes = side.wait()
        finally:
            side.close()
    finally:
        for k in ("CRASH_METHOD", "CRASH_KIND", "CRASH_DTYPE", "CRASH_HOW"):
            os.environ.pop(k)
    assert notes == {"stability": ""}, notes
    g = _configs(tmp_path / STABILITY_DIR / "results.csv")
    failed = g[g.outcome == "failed"]
    assert len(failed) == 1 and failed.iloc[0].reason.startswith(CRASHED), failed
    row = failed.iloc[0]
    assert (row["backend"], row["method"], row["dtype"]) == ("crashy", "sphere_trace", "float64")
    ok = g[g.outcome == "ok"]
    assert (ok.backend == "numpy").sum() == (ok.backend == "crashy").sum() + 1 > 10


def test_a_configuration_hung_in_native_code_is_killed_and_recorded_as_a_timeout(tmp_path):
    """``--timeout`` interrupts Python code at once and a kernel when it returns; one that never
    returns held the run forever.  Now the supervisor kills the process once the configuration has
    run factor × the limit + seconds (``supervise.HUNG_AFTER``, shortened here through its
    environment variable), and the resumed run records it as a Timeout row."""
    out = tmp_path / "run"
    env = {**os.environ, "CRASH_METHOD": "sphere_trace", "CRASH_KNOB": "tol=1e-08", "CRASH_HOW": "hang",
           supervise.HUNG_AFTER_ENV: HUNG_AFTER}
    p = bench_cli("run", "--backend", f"{CRASHY},numpy", *HANG_RUN, *QUIET, "--out", out, env=env)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    # (the second process may have claimed it: then the first process kills that one, and says so)
    assert "is stuck in" in p.stdout + p.stderr, p.stdout[-2000:] + p.stderr[-2000:]
    g = _configs(out / "results.csv")
    failed = g[g.outcome == "failed"]
    assert len(failed) == 1 and "tol=1e-08" in failed.iloc[0].knob, failed
    assert failed.iloc[0].reason.startswith("Timeout:") and "killed after" in failed.iloc[0].reason
    assert (g[g.backend == "numpy"].outcome == "ok").sum() == (g[g.backend == "crashy"].outcome == "ok").sum() + 1


def test_overdue_reads_the_note_and_the_limit(tmp_path, monkeypatch):
    """A note is overdue past factor × limit + seconds of its start, never without a limit; a
    missing or torn note is not."""
    from bench.run.results import write_json

    monkeypatch.delenv(supervise.HUNG_AFTER_ENV, raising=False)
    factor, extra = supervise.HUNG_AFTER
    path = tmp_path / INFLIGHT
    assert supervise.overdue(path) is None
    write_json(path, {"key": ["a"], "what": "w", "started": 1000.0, "limit_s": 10.0})
    assert supervise.overdue(path, now=1000.0 + factor * 10 + extra - 1) is None
    hung = supervise.overdue(path, now=1000.0 + factor * 10 + extra + 1)
    assert hung["what"] == "w" and hung["hung_s"] == pytest.approx(factor * 10 + extra + 1)
    write_json(path, {"key": ["a"], "started": 0.0, "limit_s": 0.0})
    assert supervise.overdue(path, now=1e9) is None
    path.write_text("{torn")
    assert supervise.overdue(path, now=1e9) is None


@pytest.mark.parametrize("text", ["{torn", "[1, 2]", '{"key": 5}', '{"key": null}'])
def test_a_torn_or_malformed_note_records_nothing_and_is_removed(tmp_path, text):
    """A note the killed process left half-written (or one not written by a runner) names no
    configuration: the resumed run records no crash from it and removes it."""
    from bench.run.runner import crashed_rows

    path = tmp_path / INFLIGHT
    path.write_text(text)
    assert crashed_rows(tmp_path, "r", [], set(), {}) == []
    assert not path.exists()


def test_the_side_directory_is_the_stability_stages():
    from bench.report.tables import STABILITY_DIR

    assert supervise.SIDE_DIR == STABILITY_DIR


def test_a_hung_configuration_on_a_cluster_worker_is_a_timeout_row(tmp_path):
    """On ``--cluster`` a configuration runs in a worker's thread, which the time limit interrupts
    only between bytecodes: one stuck in native code held the run forever.  Now the client cancels
    it once it has run ``supervise.HUNG_AFTER`` past the limit, restarts its worker, and records a
    Timeout row; the other configurations run."""
    pytest.importorskip("distributed")
    out = tmp_path / "run"
    env = {**os.environ, "CRASH_METHOD": "sphere_trace", "CRASH_KNOB": "tol=1e-08", "CRASH_HOW": "hang",
           supervise.HUNG_AFTER_ENV: HUNG_AFTER}
    p = bench_cli("run", "--backend", f"{CRASHY},numpy", *HANG_RUN, "--cluster", "local:2", *QUIET, "--out", out,
                  env=env)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    g = _configs(out / "results.csv")
    failed = g[g.outcome == "failed"]
    assert len(failed) == 1 and "tol=1e-08" in failed.iloc[0].knob, failed
    assert failed.iloc[0].reason.startswith("Timeout:") and "killed after" in failed.iloc[0].reason
    assert (g[g.backend == "numpy"].outcome == "ok").sum() == (g[g.backend == "crashy"].outcome == "ok").sum() + 1


def test_a_user_field_that_ends_the_process_at_planning_costs_its_own_case(tmp_path):
    """A user field calling ``os._exit(0)`` or ``os.abort()`` while planning computed its reference
    answers ended ``bench run`` with the field's own exit status (0, or 134), no rows, the healthy
    case beside it lost and nothing to resume (probe of 2026-11-30).  Now the planning note names
    the case, the supervisor resumes the run, and that case's rows are skipped with the reason."""
    (tmp_path / "ending_fields.py").write_text(textwrap.dedent('''
        import os
        from reference import Case, CallableField, rays

        o, d = rays.pinhole(eye=(0, 0, 3), look_at=(0, 0, 0), fov_deg=40, width=8, height=8)

        def good(x, xp):
            return xp.sqrt(xp.sum(x * x, axis=-1)) - 1.0

        def exits(x, xp):
            os._exit(0)

        def aborts(x, xp):
            os.abort()

        CASES = [Case(id=f"user.{f.__name__}.cam", scene=CallableField(f, lipschitz=1.0, name=f"ending.{f.__name__}"),
                      origins=o, directions=d, t_min=0.0, t_max=6.0) for f in (good, exits, aborts)]
    '''))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")])}
    out = tmp_path / "run"
    p = bench_cli("run", "--cases", "ending_fields:CASES", "--case", "user.*", "--backend", "numpy", "--method",
                  "hybrid_secant", "--accuracy-only", "--no-reference-cache", *QUIET, "--out", out, env=env)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    assert "while running planning user." in p.stderr
    rows = pd.read_csv(out / "results.csv").drop_duplicates("case_id").set_index("case_id")
    assert rows.loc["user.good.cam", "outcome"] == "ok"
    for cid, how in (("user.exits.cam", "exit status 0"), ("user.aborts.cam", "SIGABRT")):
        assert rows.loc[cid, "outcome"] == "skipped" and how in rows.loc[cid, "reason"], rows.loc[cid, "reason"]
    assert not (out / INFLIGHT).exists()
