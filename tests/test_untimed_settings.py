"""Runs that time nothing (the stability stage, ``--accuracy-only``) use each backend's optional
``untimed_settings()`` hook (:func:`bench.run.environment.untimed_backend`): a copy of the backend
with driver settings that give the same per-ray results at less compile cost (jax: one compaction
level), recorded with every row; the caller's object keeps its settings, and a hook that fails
costs the backend the saving, never its rows."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pandas as pd
import pytest

from bench.run import runner
from bench.run.environment import driver_record, untimed_backend
from bench.run.suites import Suite
from bench.run.timing import TimingPolicy
from impls import registry
from impls.protocol import Status


@dataclasses.dataclass(frozen=True)
class _Settings:
    levels: int = 3

    def record(self):
        return {"driver": "fake", "levels": self.levels}


class _Configurable:
    settings = _Settings()

    def configure(self, **changes):
        self.settings = dataclasses.replace(self.settings, **changes)


class _Offers(_Configurable):
    def untimed_settings(self):
        return {"levels": 1}


class _Raises(_Configurable):
    def untimed_settings(self):
        raise RuntimeError("planted")


class _NotADict(_Configurable):
    def untimed_settings(self):
        return [("levels", 1)]


class _UnknownSetting(_Configurable):
    def untimed_settings(self):
        return {"no_such_setting": 1}


def test_the_untimed_backend_is_a_configured_copy_and_the_callers_object_keeps_its_settings():
    b = _Offers()
    u = untimed_backend(b)
    assert u is not b and u.settings.levels == 1 and b.settings.levels == 3
    assert json.loads(driver_record(u))["levels"] == 1  # recorded with every row


@pytest.mark.parametrize("cls", [_Configurable, _Raises, _NotADict, _UnknownSetting])
def test_no_hook_or_a_failing_one_leaves_the_backend_as_it_is(cls):
    b = cls()
    assert untimed_backend(b) is b and b.settings.levels == 3


def test_a_backend_without_configure_is_left_alone():
    class OnlyHook:
        def untimed_settings(self):
            return {"levels": 1}

    b = OnlyHook()
    assert untimed_backend(b) is b


@pytest.mark.slow  # compiles jax kernels
def test_jax_runs_untimed_with_one_level_and_the_same_results(tmp_path):
    """An accuracy-only run records jax's one-level settings; its rows equal a timed run's (the
    levels change the compiled program, not a ray's results)."""
    pytest.importorskip("jax")
    from impls.jax import driver

    b = registry.resolve("jax:cpu")
    if isinstance(b, registry.Unavailable):
        pytest.skip(b.reason)
    u = untimed_backend(b)
    assert u.settings.last == u.settings.chunk and b.settings.last == driver.LAST
    assert driver.level_sizes(u.settings.chunk, u.settings.ratio, u.settings.last) == [u.settings.chunk]
    # the torus camera: most rays take a few steps, grazing ones hundreds (the timed run's levels compact them)
    suite = Suite(name="t", case_pattern="torus.camera.32x32", dtypes=("float64",), sweeps={"sphere_trace": [{}]},
                  methods=("sphere_trace",))
    frames = {}
    for accuracy_only in (True, False):
        policy = TimingPolicy(min_repeats=1, min_time_s=0.0, min_sample_s=0.0, warmup=0, timeout_s=0,
                              accuracy_only=accuracy_only)
        frames[accuracy_only] = runner.run(suite, {"jax:cpu": b}, tmp_path / str(accuracy_only), policy=policy)
    untimed, timed = frames[True], frames[False]
    assert json.loads(untimed["driver_json"].iloc[0])["last"] == b.settings.chunk
    assert json.loads(timed["driver_json"].iloc[0])["last"] == driver.LAST  # the caller's backend is unchanged
    assert set(untimed["outcome"]) == {"ok"}
    depth = untimed[untimed["quantity"] == "depth"].iloc[0]
    assert depth["evals_max"] > 20 * depth["evals_per_ray"]  # a long tail: what the levels are for
    cols = ["quantity", "status_counts", "error_max", "error_p99", "n_false_hit", "n_false_miss", "evals_per_ray",
            "evals_max", "iterations_max"]
    pd.testing.assert_frame_equal(untimed[cols].reset_index(drop=True), timed[cols].reset_index(drop=True))


@pytest.mark.slow  # compiles numba kernels
@pytest.mark.parametrize("case_id", ["csg.union.camera.32x32", "mlp.camera.32x32"])
def test_numba_runs_untimed_without_the_marcher_kernels_and_the_same_results(case_id, monkeypatch):
    """numba's untimed settings run the constant-step marchers by the core array algorithm on the
    compiled φ kernel (with dφ/dt for Newton's), as the certified methods, instead of the per-ray
    marcher kernels (``march_one``, the lanes kernel): no marcher kernel is called, and every
    ray's depth, status and counts are the same, bit for bit, for each refiner, at the default
    knobs, at another step and tolerance and with ladder steps (the MLP's φ sums its layers in the
    same order in both: the same compiled φ)."""
    pytest.importorskip("numba")
    from impls.numba import driver as nb_driver
    from reference.cases import get_case

    b = registry.resolve("numba")
    if isinstance(b, registry.Unavailable):
        pytest.skip(b.reason)
    u = untimed_backend(b)
    assert u.settings.per_ray is False and b.settings.per_ray is True
    assert json.loads(driver_record(u))["lanes"] == 0 and json.loads(driver_record(b))["lanes"] > 1
    for field in ("lanes", "per_ray"):
        for bad in (0, 1, "no"):
            with pytest.raises(ValueError, match=field):
                u.configure(**{field: bad})
    case = get_case(case_id)
    kernels = nb_driver.kernels

    def array_path_only(key, parallel=True):  # the untimed runs must not call a per-ray marcher kernel
        ks = dict(kernels(key, parallel))
        for name in ("march", "lanes"):
            ks[name] = None
        return ks

    for method in ("march_bisect", "march_secant", "march_newton"):
        for knobs in ({}, {"step": 0.37, "xtol": 1e-11}, {"ladder": 16, "ladder_after": 8}):
            got = []
            for backend in (b, u):
                with monkeypatch.context() as patch:
                    if backend is u:
                        patch.setattr(nb_driver, "kernels", array_path_only)
                    p = backend.prepare(method, case.scene, case.origins, case.directions, t_min=case.t_min,
                                        t_max=case.t_max, **knobs)
                    got.append(p.result(p.run()))
            per_ray, array = got
            # rays that hit: the refiners ran (the MLP's loose bound certifies no march's crossing as
            # the first, so its hits are UNCERTIFIED with their refined depths: ConstantStep)
            refined = (per_ray.status == Status.CONVERGED) | ((per_ray.status == Status.UNCERTIFIED) & np.isfinite(per_ray.t))
            assert refined.sum() > 50
            for k in ("t", "status", "iterations", "evals"):
                np.testing.assert_array_equal(getattr(array, k), getattr(per_ray, k), err_msg=f"{method} {knobs} {k}")
