"""The engine plug-ins (impls/warp, impls/mitsuba): what they compute, checked against numpy's
root finders and the exact references, and what they decline.

* Warp's root finders run numpy's compacting driver with φ as a Warp kernel: the same statuses,
  evaluation counts and depths as the numpy backend, ray by ray (φ is bit for bit numba's).
* ``raycast`` (Warp's mesh query, Mitsuba's sdfgrid and Mesh intersection) is float32: no false
  hit or miss on the camera cases, and every hit within float32's √ε · max(1, T) of the exact
  depth — the tolerance the stability matrix judges a float32 row by (:mod:`bench.studies.stability`).
"""

from __future__ import annotations

import importlib.util
import math

import numpy as np
import pytest

from impls import METHODS, Declined, Status, registry
from reference.cases import get_case

pytestmark = pytest.mark.slow  # compiles Warp kernels and Dr.Jit kernels

SQRT_EPS32 = math.sqrt(float(np.finfo(np.float32).eps))


def _warp():
    if importlib.util.find_spec("warp") is None:
        pytest.skip("warp-lang is not installed (pip install -c constraints.txt -e '.[engines]')")
    from impls.warp.backend import WarpBackend

    return WarpBackend("cpu")


def _mitsuba():
    if importlib.util.find_spec("mitsuba") is None or importlib.util.find_spec("drjit") is None:
        pytest.skip("mitsuba/drjit are not installed (pip install -c constraints.txt -e '.[engines]')")
    from impls.mitsuba import backend

    if "llvm" not in backend.MitsubaBackend.capabilities.devices:
        pytest.skip(f"mitsuba:llvm is unavailable here: {backend._LLVM_PROBLEM}")
    return backend.MitsubaBackend("llvm")


def _run(b, method, case, dtype="float64", **kw):
    p = b.prepare(method, case.scene, case.origins, case.directions, dtype=dtype, t_min=case.t_min,
                  t_max=case.t_max, **kw)
    out = p.run()
    b.synchronize(out)
    return p.result(out)


@pytest.mark.parametrize("case_id", ["torus.camera.32x32", "csg.union.camera.32x32", "csg.difference.camera.32x32",
                                     "torus.grazing.1e-9", "box.camera.32x32", "grid.torus32.camera.32x32",
                                     "grid.torus64.grazing.1e-6"])
@pytest.mark.parametrize("method", ["sphere_trace", "hybrid_secant", "march_bisect", "march_secant", "march_newton"])
def test_warp_root_finders_agree_with_numpy_ray_by_ray(method, case_id):
    b, ref = _warp(), registry.resolve("numpy")
    case = get_case(case_id)
    w, n = _run(b, method, case), _run(ref, method, case)
    np.testing.assert_array_equal(w.status, n.status)
    if any(type(node).__name__ == "Transform" for node in case.scene.walk()):
        # numpy sums a rotation's product in BLAS, Warp (like numba) in order: φ agrees to rounding, so
        # the iterates (and a secant's step count) may differ, the certified depths to ~1e-15
        np.testing.assert_allclose(w.t, n.t, rtol=0, atol=1e-12)
    else:  # φ bit for bit numpy's: the same iterates, counts and depths
        np.testing.assert_array_equal(w.evals, n.evals)
        np.testing.assert_array_equal(w.iterations, n.iterations)
        np.testing.assert_array_equal(w.t, n.t)
    if "camera" in case_id:  # (plain sphere tracing spends its budget on every grazing ray: MAX_ITER)
        assert (w.status == Status.CONVERGED).any() and (w.status == Status.MISS).any()


def _judge_raycast(r, case):
    """No false hit or miss; hits within float32's √ε·max(1, T) (T: the case's largest exact depth)."""
    exact = case.scene.first_hit(case.origins, case.directions, case.t_min)
    hit = np.isfinite(exact)
    got = r.status == Status.CONVERGED
    assert set(np.unique(r.status).tolist()) <= {int(Status.CONVERGED), int(Status.MISS)}
    assert np.array_equal(got, hit), f"false hits {np.sum(got & ~hit)}, false misses {np.sum(~got & hit)}"
    assert np.all(np.isinf(r.t[~got]))
    tol = SQRT_EPS32 * max(1.0, float(np.max(exact[hit])))
    err = np.abs(r.t[hit] - exact[hit])
    assert err.max() <= tol, f"max depth error {err.max():.3g} > {tol:.3g}"
    assert err.max() > 0  # float32, not the reference's float64 (a test that could not fail otherwise)
    assert np.all(r.evals == 0) and np.all(r.iterations == 0)


@pytest.mark.parametrize("case_id", ["mesh.torus.camera.32x32", "mesh.blob.camera.32x32", "mesh.fin.camera.32x32"])
def test_warp_raycast_on_meshes_matches_the_exact_hits_in_float32(case_id):
    case = get_case(case_id)
    _judge_raycast(_run(_warp(), "raycast", case, dtype="float32"), case)


@pytest.mark.parametrize("case_id", ["grid.torus32.camera.32x32", "grid.torus64.camera.32x32",
                                     "mesh.torus.camera.32x32", "mesh.blob.camera.32x32"])
def test_mitsuba_raycast_matches_the_exact_hits_in_float32(case_id):
    case = get_case(case_id)
    _judge_raycast(_run(_mitsuba(), "raycast", case, dtype="float32"), case)


@pytest.mark.parametrize("engine", ["warp", "mitsuba"])
def test_raycast_searches_t_min_to_t_max_and_flags_bad_rays(engine):
    """A window that excludes the first hit gives the next one or a MISS, never a hit outside it;
    a NaN origin or a zero direction is BAD_INPUT with t NaN."""
    b = _warp() if engine == "warp" else _mitsuba()
    case = get_case("mesh.torus.camera.32x32")
    exact = case.scene.first_hit(case.origins, case.directions, 0.0)
    hit = np.isfinite(exact)
    o, d = case.origins[hit][:50], case.directions[hit][:50]
    t0 = exact[hit][:50]
    late = b.prepare("raycast", case.scene, o, d, dtype="float32", t_min=float(t0.max()) + 1e-3, t_max=10.0)
    r = late.result(late.run())
    after = case.scene.first_hit(o, d, float(t0.max()) + 1e-3)
    assert np.array_equal(r.status == Status.CONVERGED, np.isfinite(after))
    assert np.all(r.t[r.status == Status.CONVERGED] >= t0.max())
    short = b.prepare("raycast", case.scene, o, d, dtype="float32", t_min=0.0, t_max=float(t0.min()) * 0.99)
    assert np.all(short.result(short.run()).status == Status.MISS)
    o2, d2 = o[:3].copy(), d[:3].copy()
    o2[0, 1] = np.nan
    d2[1] = 0.0
    p = b.prepare("raycast", case.scene, o2, d2, dtype="float32", t_min=0.0, t_max=10.0)
    r = p.result(p.run())
    assert r.status[0] == Status.BAD_INPUT and r.status[1] == Status.BAD_INPUT and np.isnan(r.t[:2]).all()
    assert r.status[2] == Status.CONVERGED


def test_warp_declines_with_the_reason():
    b = _warp()
    grid, sphere, mesh = (get_case(c) for c in ("grid.torus32.camera.32x32", "sphere.camera.64x64",
                                                "mesh.torus.camera.16x16"))
    assert "triangle meshes" in b.declines("raycast", grid.scene)
    assert "triangle meshes" in b.declines("raycast", sphere.scene)
    assert b.declines("raycast", mesh.scene) is None
    assert b.declines("hybrid_secant", grid.scene) is None  # the grid kernel (impls.warp.grid)
    assert "MeshSDF" in b.declines("hybrid_secant", mesh.scene)
    with pytest.raises(ValueError, match="dtype='float32'"):
        b.prepare("raycast", mesh.scene, mesh.origins, mesh.directions, dtype="float64")
    with pytest.raises(Declined, match="float64"):
        b.prepare("hybrid_secant", sphere.scene, sphere.origins, sphere.directions, dtype="float32")


def test_mitsuba_declines_with_the_reason():
    b = _mitsuba()
    from reference.grid import grid_from_field
    from reference.primitives import Sphere

    open_grid = grid_from_field(Sphere((0.0, 0.0, 0.0), 1.0), (-0.5,) * 3, (0.5,) * 3, 8)  # surface leaves the box
    assert "leaves the box" in b.declines("raycast", open_grid)
    assert "neither" in b.declines("raycast", Sphere((0.0, 0.0, 0.0), 1.0))
    assert b.methods() == ("raycast",)
    assert b.capabilities.dtypes == ("float32",)


def test_raycast_is_an_engine_method_the_builtins_do_not_offer():
    spec = METHODS["raycast"]
    assert spec.family == "root" and spec.knobs == () and spec.build is None
    assert spec.description == ("the engine's own first-hit ray query (BVH over the mesh's triangles, or the "
                                "engine's SDF-grid intersector); no knobs; precision as the engine computes")
    numpy_backend = registry.resolve("numpy")
    assert "raycast" not in numpy_backend.methods()
    from bench.run.configuration import Config, skip_reason

    cfg = Config(case=get_case("mesh.torus.camera.16x16"), backend_id="numpy", method="raycast", dtype="float32",
                 knobs={})
    assert skip_reason(cfg, numpy_backend).startswith("numpy does not implement raycast")


def test_the_llvm_finder_keeps_a_users_path_and_reads_versions(monkeypatch):
    from impls.mitsuba import llvm

    assert llvm._major("/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1") == 19
    assert llvm._major("/usr/lib/x86_64-linux-gnu/libLLVM-15.so") == 15
    assert llvm._major("/usr/lib/llvm-17/lib/libLLVM.so") == 17
    assert all(m >= llvm.MIN_MAJOR for m, _ in llvm.candidates())
    monkeypatch.setenv(llvm.ENV, "/somewhere/libLLVM.so")
    assert llvm.configure() is None
    import os

    assert os.environ[llvm.ENV] == "/somewhere/libLLVM.so"


@pytest.mark.parametrize("spec, missing", [("impls.warp.backend:WarpBackend", "warp"),
                                           ("impls.mitsuba.backend:MitsubaBackend", "mitsuba")])
def test_an_engine_not_installed_is_unavailable_with_the_install_command(monkeypatch, spec, missing):
    import sys

    monkeypatch.setitem(sys.modules, missing, None)  # import warp / import mitsuba raise ImportError
    monkeypatch.delitem(sys.modules, spec.split(":")[0], raising=False)
    got = registry.resolve(spec)
    assert isinstance(got, registry.Unavailable)
    assert "pip install -c constraints.txt -e '.[engines]'" in got.reason
