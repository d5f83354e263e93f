"""Faulty plugged backends, hangs, budgets, atomic files and resume (issue 15, findings 1, 6, 11).

A user backend is user code: whatever it returns or raises, the run goes on, its configuration is a
failed row naming the fault, and no other backend loses a row.  A time budget is a guard against a
hang, never a plan: it bounds the configuration in flight, and a run that spends it says so."""

from __future__ import annotations

import dataclasses
import json
import os
import stat
import sys
import time

import numpy as np
import pandas as pd
import pytest

from bench.run import runner
from bench.run.results import OVER_BUDGET, read_results, remove_temporaries, write_results, to_frame
from bench.run.suites import Suite
from bench.run.timing import Timeout, TimingPolicy, time_limit
from impls import registry
from tests import test_bench_fakes as fakes

CASE = "sphere.camera.64x64"
FAST = TimingPolicy(min_repeats=1, min_time_s=0.0, min_sample_s=0.0, warmup=0, timeout_s=20.0, accuracy_only=True)
SUITE = Suite(name="t", case_pattern=CASE, dtypes=("float64",), sweeps={"sphere_trace": [{}],
              "hybrid_secant": [{}]}, methods=("sphere_trace", "hybrid_secant"))


def _run(tmp_path, bad, **kw):
    backends = {"numpy": registry.resolve("numpy"), "bad": bad}
    df = runner.run(SUITE, backends, tmp_path, policy=kw.pop("policy", FAST), **kw)
    env = json.loads((tmp_path / "environment.json").read_text())
    return df, env


def _numpy_rows_all_there(df):
    plan = runner.plan(SUITE, ["numpy"], None, None, None)
    np_rows = df[df["backend"] == "numpy"]
    keys = set(map(tuple, np_rows[runner.CONFIG_KEY].astype(str).itertuples(index=False, name=None)))
    assert keys == {tuple(map(str, c.key)) for c in plan}
    assert set(np_rows["outcome"]) == {"ok"}, np_rows[["outcome", "reason"]]


@pytest.mark.parametrize("cls, outcome, words", [
    (fakes.BadStatusBackend, "failed", ["[7]", "Status"]),
    (fakes.FloatStatusBackend, "failed", ["status", "non-integer"]),
    (fakes.WrongResultBackend, "failed", ["no 't'", "tuple"]),
    (fakes.MethodsRaiseBackend, "failed", ["methods() raised", "planted"]),
    (fakes.CapabilitiesRaiseBackend, "failed", ["capabilities raised", "planted"]),
    (fakes.ExitsBackend, "failed", ["Prepared.run() raised SystemExit"]),
    # (before: each of these four ended the run, every row lost and --resume stopped at the same place)
    (fakes.KeyboardInterruptBackend, "failed", ["raised KeyboardInterrupt: planted", "no Ctrl-C"]),
    (fakes.BaseExceptionBackend, "failed", ["raised OwnBaseException: planted"]),
    (fakes.CountsLieBackend, "failed", ["result evals must be whole counts in [0, 2147483647]"]),
    (fakes.FractionalEvalsBackend, "failed", ["not whole numbers"]),
    (fakes.NoCompileSBackend, "ok", []),
    (fakes.NoStatusCountsBackend, "ok", []),
    (fakes.StatusCountsLiesBackend, "ok", []),
    (fakes.VersionsRaiseBackend, "ok", []),
])
def test_a_faulty_backend_costs_only_its_own_rows(tmp_path, cls, outcome, words):
    df, env = _run(tmp_path, cls())
    _numpy_rows_all_there(df)
    bad = df[df["backend"] == "bad"]
    assert len(bad) and set(bad["outcome"]) == {outcome}, bad[["outcome", "reason"]].to_string()
    for w in words:
        assert bad["reason"].str.contains(w, regex=False).all(), (w, bad["reason"].iloc[0])
    if outcome == "ok":  # counted by the runner from the checked statuses, never by the user's method
        counts = json.loads(bad["status_counts"].iloc[0])
        assert sum(counts.values()) == bad["n_rays"].iloc[0] and "CONVERGED" in counts
    assert env["complete"] == "true"
    if cls is fakes.VersionsRaiseBackend:
        assert "planted: versions() is broken" in env["backend.bad.versions_error"]


def _assert_same_numpy_rows(mixed, alone):
    """numpy's rows of a run beside a faulty plug-in equal those of a run without it: outcome,
    error and per-ray status counts, configuration by configuration."""
    cols = ["method", "knob", "quantity", "outcome", "error_max", "status_counts"]
    ours = mixed[mixed["backend"] == "numpy"][cols].sort_values(cols[:3]).reset_index(drop=True)
    pd.testing.assert_frame_equal(ours, alone[cols].sort_values(cols[:3]).reset_index(drop=True))


def test_a_backend_writing_into_its_inputs_changes_only_its_own_rows(tmp_path):
    """A plug-in that moves the rays' origins and scales ``t_hit`` in place, run before numpy on
    each case: numpy's rows are those of a run without it, the case's rays and depths are
    unchanged, and the plug-in's own rows show its error.  Before, it was handed the case's own
    arrays: numpy's sphere_trace rows on the 64² sphere reported errors of 0.25 to 2.0, one
    more 0.25 for every configuration the plug-in had run before them."""
    from reference.cases import get_case

    case = get_case(CASE)
    o0, d0, t0 = case.origins.copy(), case.directions.copy(), case.exact_t.copy()
    suite = dataclasses.replace(SUITE, methods=("sphere_trace", "hybrid_secant", "normal"),
                                sweeps={**SUITE.sweeps, "normal": [{}]})
    mixed = runner.run(suite, {"bad": fakes.MutatingBackend(), "numpy": registry.resolve("numpy")},
                       tmp_path / "mixed", policy=FAST)
    alone = runner.run(suite, {"numpy": registry.resolve("numpy")}, tmp_path / "alone", policy=FAST)
    assert np.array_equal(case.origins, o0) and np.array_equal(case.directions, d0)
    assert np.array_equal(case.exact_t, t0, equal_nan=True)
    _assert_same_numpy_rows(mixed, alone)
    bad = mixed[mixed["backend"] == "bad"]
    assert set(bad["method"]) == {"sphere_trace", "hybrid_secant", "normal"}
    assert (bad["error_max"] > 0.1).all(), bad[["method", "error_max"]]


def test_a_backend_writing_into_the_scene_fails_its_own_rows_only(tmp_path):
    """A plug-in that scales the MLP's first weight matrix in place: a case's scene arrays are
    read-only, so its rows fail naming that, numpy's rows (run after it) equal a run without it,
    and the weights are unchanged."""
    from reference.cases import get_case

    case = get_case("mlp.camera.32x32")
    w0 = case.scene.weights["W1"].copy()
    suite = dataclasses.replace(SUITE, case_pattern="mlp.camera.32x32")
    mixed = runner.run(suite, {"bad": fakes.SceneMutatingBackend(), "numpy": registry.resolve("numpy")},
                       tmp_path / "mixed", policy=FAST)
    alone = runner.run(suite, {"numpy": registry.resolve("numpy")}, tmp_path / "alone", policy=FAST)
    assert np.array_equal(case.scene.weights["W1"], w0)
    bad = mixed[mixed["backend"] == "bad"]
    assert len(bad) and set(bad["outcome"]) == {"failed"}, bad[["outcome", "reason"]]
    assert bad["reason"].str.contains("read-only").all(), bad["reason"].iloc[0]
    _assert_same_numpy_rows(mixed, alone)


def test_a_backend_changing_its_scene_changes_only_its_own_rows(tmp_path):
    """A plug-in that sets the sphere's radius to 1.5 in ``prepare``: it was handed the case's own
    scene, and every later row of every backend ran on the larger sphere (the 2026-11-30 probe:
    68 false hits on each numpy row, blamed on numpy).  A plug-in now gets its own copy."""
    from reference.cases import get_case

    case = get_case(CASE)
    mixed = runner.run(SUITE, {"bad": fakes.SceneRebindingBackend(), "numpy": registry.resolve("numpy")},
                       tmp_path / "mixed", policy=FAST)
    alone = runner.run(SUITE, {"numpy": registry.resolve("numpy")}, tmp_path / "alone", policy=FAST)
    assert case.scene.radius == 1.0
    _assert_same_numpy_rows(mixed, alone)
    bad = mixed[mixed["backend"] == "bad"]
    assert (bad["n_false_hit"] > 0).all(), bad[["method", "n_false_hit"]]  # its own rows: the larger sphere


def test_work_moved_into_result_is_no_comparable_time(tmp_path):
    """A plug-in whose run() returns at once and whose result() does the work was timed at 0.3 µs
    and picked in "which to pick" at ×0.005 (the 2026-11-30 probe).  Its time is now not
    comparable (time_ratio_cf NaN, which no pick takes) and its timing_note says why; numpy's
    rows carry no such note."""
    timed = dataclasses.replace(FAST, accuracy_only=False, min_repeats=3)
    df = runner.run(SUITE, {"lazy": fakes.LazyResultBackend(), "numpy": registry.resolve("numpy")}, tmp_path,
                    policy=timed)
    lazy, ours = df[df["backend"] == "lazy"], df[df["backend"] == "numpy"]
    assert len(lazy) and lazy["time_ratio_cf"].isna().all()
    assert lazy["timing_note"].str.contains("Prepared.result() took", regex=False).all()
    assert ours["time_ratio_cf"].notna().all()
    assert not ours["timing_note"].fillna("").str.contains("result()", regex=False).any()


def test_a_backend_changing_library_settings_changes_only_its_own_rows(tmp_path):
    """A plug-in that sets ``np.seterr(all="raise")`` (and torch's default dtype to float32) in
    ``prepare``, run before numpy on the torus camera, whose marches underflow harmlessly: numpy's
    rows equal a run without it, and the settings are back after the run.  Before, numpy's
    sphere_trace and hybrid_secant rows there failed with FloatingPointError (underflow)."""
    suite = dataclasses.replace(SUITE, case_pattern="torus.camera.32x32")
    torch = sys.modules.get("torch")
    before = np.geterr(), (torch.get_default_dtype() if torch is not None else None)
    if torch is not None:
        torch.set_default_dtype(torch.float64)  # so that the plug-in's float32 is a change
    try:
        mixed = runner.run(suite, {"bad": fakes.GlobalStateBackend(), "numpy": registry.resolve("numpy")},
                           tmp_path / "mixed", policy=FAST)
        assert np.geterr() == before[0]
        if torch is not None:
            assert torch.get_default_dtype() == torch.float64
    finally:
        np.seterr(**before[0])
        if torch is not None:
            torch.set_default_dtype(before[1])
    alone = runner.run(suite, {"numpy": registry.resolve("numpy")}, tmp_path / "alone", policy=FAST)
    assert set(mixed[mixed["backend"] == "numpy"]["outcome"]) == {"ok"}, \
        mixed[mixed["backend"] == "numpy"][["method", "reason"]]
    _assert_same_numpy_rows(mixed, alone)


def test_a_cases_rays_are_read_only():
    from reference.cases import get_case

    case = get_case(CASE)
    with pytest.raises(ValueError, match="read-only"):
        case.origins[0, 0] = 1.0
    with pytest.raises(ValueError, match="read-only"):
        case.directions += 0.0
    # and the arrays its scene holds, children's and containers' included
    for cid, arrays in (("mlp.camera.32x32", lambda s: s.weights.values()),
                        ("grid.torus64.camera.32x32", lambda s: (s.values, s.lo, s.spacing)),
                        ("mesh.torus.camera.16x16", lambda s: (s.vertices, s.faces))):
        for a in arrays(get_case(cid).scene):
            assert not a.flags.writeable, cid


def test_a_hang_is_bounded_by_the_budget_left_and_the_run_says_it_is_incomplete(tmp_path, monkeypatch):
    monkeypatch.setattr(fakes.SleepyBackend, "SLEEP_S", 600.0)
    t0 = time.monotonic()
    df, env = _run(tmp_path, fakes.SleepyBackend(), budget_s=1.5)
    took = time.monotonic() - t0
    # sized to the work, not to the machine: had the call in flight not been interrupted, the run
    # would have lasted at least one sleep
    assert took < fakes.SleepyBackend.SLEEP_S, f"a 1.5 s budget took {took:.1f} s: the configuration in flight was not bounded"
    over = df["reason"].fillna("").str.startswith(OVER_BUDGET)
    assert over.any() and set(df.loc[over, "outcome"]) == {"skipped"}
    assert df.loc[over & (df["backend"] == "bad"), "reason"].str.contains("interrupted in flight").any()
    assert env["complete"] == "false" and OVER_BUDGET in env["incomplete_reason"]
    # nothing lost: every planned configuration has rows
    plan = runner.plan(SUITE, ["numpy", "bad"], None, None, None)
    keys = set(map(tuple, df[runner.CONFIG_KEY].astype(str).itertuples(index=False, name=None)))
    assert keys == {tuple(map(str, c.key)) for c in plan}


def test_a_hang_past_the_timeout_is_a_failed_row_and_the_run_goes_on(tmp_path, monkeypatch):
    import dataclasses

    df, env = _run(tmp_path, fakes.SleepyBackend(), policy=dataclasses.replace(FAST, timeout_s=0.3))
    _numpy_rows_all_there(df)
    bad = df[df["backend"] == "bad"]
    assert set(bad["outcome"]) == {"failed"} and bad["reason"].str.contains("time limit of 0.3 s").all()
    assert env["complete"] == "true"


def test_time_limit_interrupts_sleeps_swallowing_code_and_nests():
    # each block sleeps LONG unless a limit cuts it short, so the total bounds the work, not the
    # machine: any sleep that ran to its end takes the total past LONG
    LONG = 120
    t0 = time.monotonic()
    with pytest.raises(Timeout, match="0.2 s"):
        with time_limit(0.2):
            time.sleep(LONG)
    with pytest.raises(Timeout):
        with time_limit(0.2):
            while True:
                try:
                    time.sleep(LONG)
                except Exception:  # noqa: BLE001 - what a careless backend does
                    pass
    # an outer limit passing inside an inner one is raised (again) when the inner block swallows it
    with pytest.raises(Timeout, match="outer"):
        with time_limit(0.2, "outer"):
            try:
                with time_limit(2 * LONG, "inner"):
                    time.sleep(LONG)
            except Timeout:
                pass
            time.sleep(LONG)
    assert time.monotonic() - t0 < LONG
    with time_limit(0.5):  # a limit left in time does not fire later
        pass
    time.sleep(0.7)


@pytest.mark.parametrize("mask, mode", [(0o022, 0o644), (0o027, 0o640)])
def test_result_files_follow_the_umask(tmp_path, mask, mode):
    old = os.umask(mask)
    try:
        write_results(to_frame([{"case_id": "c", "outcome": "ok"}]), tmp_path)
    finally:
        os.umask(old)
    for name in ("results.csv", "results.parquet"):
        assert stat.S_IMODE((tmp_path / name).stat().st_mode) == mode, name


def test_resume_ignores_and_removes_temporaries_and_adds_up_sessions(tmp_path):
    df, env = _run(tmp_path, fakes.NoCompileSBackend(), budget_s=0.0)
    assert env["complete"] == "false"
    first = json.loads(env["elapsed_sessions_s"])
    assert len(first) == 1
    # what a SIGKILL during a write leaves: 0-byte temporaries of the atomic writer (bench.run.results.write_atomic)
    for name in (".results.csv.1a2b3c4d.tmp", ".results.parquet.deadbeef.tmp", ".claims.csv.x1y2z3.tmp"):
        (tmp_path / name).write_bytes(b"")
    assert len(read_results(tmp_path)) == len(df)  # a temporary is never read as results
    df2, env2 = _run(tmp_path, fakes.NoCompileSBackend(), resume=True)
    assert not list(tmp_path.glob(".*.tmp"))
    assert env2["complete"] == "true" and "incomplete_reason" not in env2
    sessions = json.loads(env2["elapsed_sessions_s"])
    assert len(sessions) == 2 and sessions[0] == first[0]
    assert float(env2["elapsed_s"]) == pytest.approx(sum(sessions), abs=0.11)
    assert set(df2["outcome"]) == {"ok"}
    assert remove_temporaries(tmp_path) == []


def test_registry_tells_unknown_ids_from_broken_backends():
    for bid in ("nosuch", "nosuch.module:Backend", "nosuchmodule:Backend", "tests.test_bench_fakes:NoSuchAttr",
                ":Backend", "tests.test_bench_fakes:"):
        b = registry.resolve(bid)
        assert isinstance(b, registry.Unavailable) and b.unknown, (bid, b)
    b = registry.resolve("tests.test_bench_fakes:BrokenFactoryBackend")
    assert isinstance(b, registry.Unavailable) and not b.unknown and "planted" in b.reason
    assert not isinstance(registry.resolve("tests.test_bench_fakes:BadStatusBackend"), registry.Unavailable)


def test_a_ctrl_c_is_told_apart_from_a_plugins_own_keyboard_interrupt():
    """While a run watches SIGINT (bench.run.interrupts), a KeyboardInterrupt raised by code is a
    fault of that code, and one raised by a real SIGINT stops the run."""
    import signal
    import threading

    from bench.run import interrupts

    if threading.current_thread() is not threading.main_thread():
        pytest.skip("signals are handled in the main thread")
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with interrupts.watching():
            try:
                raise KeyboardInterrupt("planted")
            except KeyboardInterrupt as exc:
                assert interrupts.is_fault(exc)
            with pytest.raises(KeyboardInterrupt) as info:
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(5)
            assert not interrupts.is_fault(info.value)
        # not watching: every KeyboardInterrupt stops the run (it cannot be told apart) ...
        assert not interrupts.is_fault(KeyboardInterrupt("planted"))
        # ... unless SIGINT is ignored (a background job of a script): then none is a Ctrl-C.  (The
        # README's test command started so crashed its xdist worker on the planted
        # KeyboardInterruptBackend: watching() found SIG_IGN and took every KeyboardInterrupt
        # for a Ctrl-C.)
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        with interrupts.watching():
            assert interrupts.is_fault(KeyboardInterrupt("planted"))
    finally:
        signal.signal(signal.SIGINT, old)
    # off the main thread (a --cluster worker's task) no KeyboardInterrupt is a Ctrl-C: Python raises
    # those in the main thread only (before, a plug-in's own killed the dask worker four times)
    seen = []
    worker = threading.Thread(target=lambda: seen.append(interrupts.is_fault(KeyboardInterrupt("planted"))))
    worker.start()
    worker.join()
    assert seen == [True]
