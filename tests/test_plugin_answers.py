"""An untrusted plug-in's answers and process state, as the 2026-12-01 plug-in probe found them
(scratch/s76/probeP): each test fails on the code before that probe's fixes.

* the calls a row times must give the answer its accuracy judges (a plug-in that computed once,
  then returned garbage fast, was picked at ×0.001 with numpy's errors);
* complex outputs, boolean statuses, float64 or float16 answers in a float32 configuration, and a
  CONVERGED ray with no evaluation counted are faults naming the array;
* an ``id`` that changes between reads, and a loop driver whose settings or ``configure`` raise,
  make the plug-in unavailable instead of passing for a built-in or ending the run;
* the working directory, the recursion limit and ``sys.stdout`` are put back after a configuration;
* a ``versions()`` that raises a BaseException or hangs is recorded, not the end of the run."""

from __future__ import annotations

import os
import sys
import time

import numpy as np
import pytest

from bench.run import runner
from bench.run.contract import BackendFault, answers_differ, check_result, library_state_kept
from bench.run.suites import Suite
from bench.run.timing import TimingPolicy
from impls import Prepared, RayResult, Status, registry
from tests.plugin_backend import PluginBackend

SUITE = Suite(name="t", case_pattern="sphere.camera.64x64", dtypes=("float64",),
              sweeps={"hybrid_secant": [{}]}, methods=("hybrid_secant",))
TIMED = TimingPolicy(min_repeats=3, min_time_s=0.0, min_sample_s=0.0, warmup=0)


class LaterCallsDiffer(PluginBackend):
    """numpy's answer on the first call; from the second on, every depth moved by ``SHIFT``."""

    SHIFT = 1e-3

    def __init__(self, device: str = "cpu"):
        super().__init__(device)
        self.id = "later-differ"

    def prepare(self, method, scene, origins, directions, **kwargs):
        p = self._inner.prepare(method, scene, origins, directions, **kwargs)
        calls = [0]

        def run():
            calls[0] += 1
            return p.run(), calls[0]

        def result(out):
            r = p.result(out[0])
            shift = 0.0 if out[1] == 1 else self.SHIFT
            return RayResult(t=np.asarray(r.t) + shift, status=r.status, iterations=r.iterations, evals=r.evals,
                             outputs=dict(r.outputs))

        return Prepared(run=run, result=result)


class SameEveryCall(LaterCallsDiffer):
    SHIFT = 0.0


def test_the_calls_timed_must_give_the_answer_the_row_judges(tmp_path):
    df = runner.run(SUITE, {"later-differ": LaterCallsDiffer()}, tmp_path / "a", policy=TIMED)
    assert set(df["outcome"]) == {"failed"}, df[["outcome", "reason"]]
    assert df["reason"].str.contains("the timed calls did not give the answer of the checked (first) call: t "
                                     "differs on", regex=False).all(), df["reason"].iloc[0]
    ok = runner.run(SUITE, {"same": SameEveryCall()}, tmp_path / "b", policy=TIMED)
    assert set(ok["outcome"]) == {"ok"}, ok[["outcome", "reason"]]


def _result(n=8, **kw) -> RayResult:
    base = dict(t=np.full(n, 2.0), status=np.zeros(n, np.int64), iterations=np.ones(n, np.int64),
                evals=np.ones(n, np.int64), outputs={})
    return RayResult(**{**base, **kw})


def test_answers_differ_within_rounding_is_one_answer():
    a = _result(outputs={"normal": np.ones((8, 3))})
    assert answers_differ(a, _result(outputs={"normal": np.ones((8, 3)) * (1 + 1e-14)}), "float64") == ""
    assert "output normal differs on 1 of 24" in answers_differ(
        a, _result(outputs={"normal": np.where(np.arange(24).reshape(8, 3) == 5, 1.5, 1.0)}), "float64")
    assert "status differs" in answers_differ(a, _result(status=np.ones(8, np.int64),
                                                         outputs={"normal": np.ones((8, 3))}), "float64")
    nan = _result(t=np.full(8, np.nan))
    assert answers_differ(nan, _result(t=np.full(8, np.nan)), "float64") == ""


def test_a_complex_output_or_a_boolean_status_is_a_fault():
    with pytest.raises(BackendFault, match="output normal has dtype complex128, expected real numbers"):
        check_result(_result(outputs={"normal": np.ones((8, 3)) + 5j}), 8, ("normal",))
    with pytest.raises(BackendFault, match="result status has dtype bool"):
        check_result(_result(status=np.zeros(8, bool)), 8, ())


def test_a_float32_configuration_takes_float32_answers_only():
    wide = np.linspace(1.0, 2.0, 8)  # float64 values float32 cannot hold
    with pytest.raises(BackendFault, match="result t holds values float32 cannot represent in a float32 configuration"):
        check_result(_result(t=wide), 8, (), dtype="float32")
    with pytest.raises(BackendFault, match="result t has dtype float16 in a float32 configuration"):
        check_result(_result(t=wide.astype(np.float16)), 8, (), dtype="float32")
    check_result(_result(t=wide.astype(np.float32)), 8, (), dtype="float32")
    check_result(_result(t=wide.astype(np.float32).astype(np.float64)), 8, (), dtype="float32")  # widened: fine
    with pytest.raises(BackendFault, match="output color holds values float32 cannot represent"):
        check_result(_result(outputs={"color": np.full((8, 3), 0.1)}), 8, ("color",), dtype="float32")


def test_a_root_finders_hit_with_no_evaluation_counted_is_a_fault():
    zero = _result(evals=np.zeros(8, np.int64))
    with pytest.raises(BackendFault, match="8 rays are CONVERGED with no evaluation of φ counted"):
        check_result(zero, 8, (), evaluates=True)
    check_result(zero, 8, ())  # an engine's own query counts none
    check_result(_result(evals=np.zeros(8, np.int64), status=np.full(8, int(Status.MISS), np.int64), t=np.full(8, np.inf)), 8, (),
                 evaluates=True)  # MISS rays may finish before any evaluation


class ShiftingId(PluginBackend):
    """An id that reads as a plug-in's once and as torch's after."""

    def __init__(self, device: str = "cpu"):
        super().__init__(device)
        self._reads = 0

    @property
    def id(self):
        self._reads += 1
        return "p-shift" if self._reads == 1 else "torch:cpu"

    @id.setter
    def id(self, value):
        pass


class ConfigureRaises(PluginBackend):
    def __init__(self, device: str = "cpu"):
        super().__init__(device)
        self.id = "configure-raises"
        self.settings = self._inner.settings

    def configure(self, **kw):
        raise ValueError("planted: one thread only")


def test_an_id_that_changes_between_reads_or_a_failing_driver_makes_the_plugin_unavailable():
    from bench.commands._common import resolve_backends

    b = registry.resolve("tests.test_plugin_answers:ShiftingId")
    assert isinstance(b, registry.Unavailable) and "changes from one read to the next" in b.reason, b
    backends, msg = resolve_backends(["tests.test_plugin_answers:ConfigureRaises", "numpy"], 1)
    assert msg == ""
    bad = backends["configure-raises"]
    assert isinstance(bad, registry.Unavailable) and "configuring its loop driver" in bad.reason, bad
    assert "ValueError: planted: one thread only" in bad.reason and not isinstance(backends["numpy"],
                                                                                registry.Unavailable)


def test_the_working_directory_recursion_limit_and_stdout_are_put_back(tmp_path):
    cwd, limit, out = os.getcwd(), sys.getrecursionlimit(), sys.stdout
    with library_state_kept():
        os.chdir(tmp_path)
        sys.setrecursionlimit(limit + 1000)
        sys.stdout = open(os.devnull, "w")
    try:
        assert (os.getcwd(), sys.getrecursionlimit(), sys.stdout) == (cwd, limit, out)
    finally:
        os.chdir(cwd)
        sys.setrecursionlimit(limit)
        sys.stdout = out


class _Stop(BaseException):
    pass


class VersionsStop(PluginBackend):
    def versions(self):
        raise _Stop("planted")


class VersionsHang(PluginBackend):
    def versions(self):
        time.sleep(30)
        return {}


def test_a_versions_that_raises_a_base_exception_or_hangs_is_recorded(monkeypatch):
    assert runner._versions("v", VersionsStop()) == {"backend.v.versions_error": "_Stop: planted"}
    monkeypatch.setattr(runner, "VERSIONS_LIMIT_S", 0.2)
    started = time.monotonic()
    got = runner._versions("h", VersionsHang())
    assert got["backend.h.versions_error"].startswith("Timeout: ran past the time limit of 0.2 s (a backend's "
                                                      "versions())"), got
    assert time.monotonic() - started < 25  # (cut short, not slept out)


class SetsSeterr(PluginBackend):
    def prepare(self, method, scene, origins, directions, **kwargs):
        np.seterr(all="raise")
        return super().prepare(method, scene, origins, directions, **kwargs)


def test_a_later_rounds_change_of_library_settings_is_put_back():
    """Before: ``--rounds``' extra rounds ran outside the settings' restore: a plug-in's
    ``np.seterr(all="raise")`` in round 2 failed numpy's round-2 timings."""
    from bench.run.configuration import retime
    from bench.run.plan import Config
    from reference import get_case

    before = np.geterr()
    cfg = Config(get_case("sphere.camera.64x64"), "npwrap", "hybrid_secant", "float64", {})
    got = retime(cfg, SetsSeterr(), TimingPolicy(min_repeats=1, min_time_s=0.0, min_sample_s=0.0, warmup=0))
    assert isinstance(got, list) and np.geterr() == before, got
