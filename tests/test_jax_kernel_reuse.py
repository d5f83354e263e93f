"""The jax backend compiles one kernel per method and structure: knobs it can trace are runtime
arguments (:meth:`impls.jax.backend.JaxBackend.compile_configuration`), so a tolerance sweep
reuses one kernel, and a reused kernel gives exactly what a kernel compiled for the setting
gives, in float32 too (a traced knob is weakly typed, as the constant it replaces)."""

from __future__ import annotations

import numpy as np
import pytest

from impls import Status
from reference import Sphere
from tests.conftest import resolve_or_skip


def _rays(n=32):
    rng = np.random.default_rng(0)
    o = np.tile([0.0, 0.0, -3.0], (n, 1))
    d = np.column_stack([rng.uniform(-0.2, 0.2, n), rng.uniform(-0.2, 0.2, n), np.ones(n)])
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


def _result(backend, scene, o, d, dtype, **knobs):
    prep = backend.prepare("sphere_trace", scene, o, d, dtype=dtype, t_min=0.0, t_max=10.0, **knobs)
    return prep, prep.result(prep.run())


@pytest.mark.slow  # compiles jax kernels
@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_a_tolerance_sweep_reuses_one_kernel_with_the_results_of_its_own(dtype, monkeypatch):
    from impls.jax import backend as jb

    scene, (o, d) = Sphere(center=(0.0, 0.0, 0.0), radius=1.0), _rays()
    shared = resolve_or_skip("jax:cpu")
    first, _ = _result(shared, scene, o, d, dtype, tol=1e-6)
    second, got = _result(shared, scene, o, d, dtype, tol=1e-3)
    assert first.compile_cache in (None, "compiled", "reused") and second.compile_cache == "reused"
    # (the traced knob names and compiled-in knobs of each kernel, should there be more than one)
    assert len(shared._kernels) == 1, [(k[4], k[5]) for k in shared._kernels]
    # the setting compiled into a kernel of its own (no knob traced): the same rays, bit for bit
    monkeypatch.setattr(jb, "_traced_sets", lambda method, knobs: [()])
    _, want = _result(resolve_or_skip("jax:cpu"), scene, o, d, dtype, tol=1e-3)
    for k in ("t", "status", "iterations", "evals"):
        np.testing.assert_array_equal(getattr(got, k), getattr(want, k), err_msg=k)
    # and the setting matters: the other tolerance, through the same kernel, iterates differently
    assert (got.status == Status.CONVERGED).all()
    assert np.any(got.iterations != _result(shared, scene, o, d, dtype, tol=1e-6)[1].iterations)


@pytest.mark.slow  # compiles jax kernels
def test_a_different_structure_compiles_its_own_kernel():
    b = resolve_or_skip("jax:cpu")
    o, d = _rays()
    _result(b, Sphere(center=(0.0, 0.0, 0.0), radius=1.0), o, d, "float64")
    # a kernel of its own is a new entry of the backend's table (its compile_cache may still say
    # "reused": jax's persistent cache on disk can hold it from an earlier session)
    _result(b, Sphere(center=(0.0, 0.0, 0.0), radius=0.5), o, d, "float64")  # a parameter compiled in
    assert len(b._kernels) == 2
    _result(b, Sphere(center=(0.0, 0.0, 0.0), radius=0.5), o[:16], d[:16], "float64")  # another shape
    assert len(b._kernels) == 3
    _result(b, Sphere(center=(0.0, 0.0, 0.0), radius=0.5), o, d, "float64", max_steps=64)  # an int knob
    assert len(b._kernels) == 4
