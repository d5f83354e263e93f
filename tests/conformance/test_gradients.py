"""Normals, curvatures and dt/dθ at given hits against exact answers."""

from __future__ import annotations

import numpy as np
import pytest

from impls import Status
from reference.rays import normalize
from tests.conformance.common import SCENES, SPHERE, hits, run, tol_for


@pytest.mark.parametrize("scene_name", ["sphere", "algebraic"])
def test_normal_against_exact(any_backend, scene_name):
    scene = SCENES[scene_name]
    o, d, t, hit, x = hits(scene)
    r = run(any_backend, "normal", scene, o, d, t_hit=t)
    assert np.all(r.status[hit] == Status.CONVERGED) and np.all(r.status[~hit] == Status.MISS)
    assert np.all(np.isnan(r.outputs["normal"][~hit]))
    err = np.abs(r.outputs["normal"][hit] - scene.normal_exact(x[hit])).max()
    assert err <= tol_for(any_backend, 1e-14, 1e-9), err


@pytest.mark.parametrize("scene_name", ["sphere", "algebraic"])
def test_curvatures_against_exact(any_backend, scene_name):
    scene = SCENES[scene_name]
    o, d, t, hit, x = hits(scene)
    r = run(any_backend, "curvature", scene, o, d, t_hit=t)
    k1, k2 = scene.curvatures_exact(x[hit])
    tol = tol_for(any_backend, 1e-12, 1e-6)
    np.testing.assert_allclose(r.outputs["curvature_divergence"][hit], k1 + k2, rtol=0, atol=tol)
    np.testing.assert_allclose(r.outputs["gaussian_curvature"][hit], k1 * k2, rtol=0, atol=tol)
    lap = scene.laplacian_exact(x[hit]) if hasattr(scene, "laplacian_exact") else k1 + k2
    np.testing.assert_allclose(r.outputs["curvature_laplacian"][hit], lap, rtol=0, atol=tol)
    if scene_name == "algebraic":  # the two curvatures differ for a non-SDF, and both are kept
        assert np.all(np.abs(r.outputs["curvature_laplacian"][hit] - r.outputs["curvature_divergence"][hit]) > 1)


def test_normal_and_curvatures_of_a_plane_are_exact(any_backend):
    """A linear field has a constant gradient and a zero Hessian: backends whose autodiff drops
    such outputs from the graph must still answer (torch raised on the plane before)."""
    from reference import Plane

    scene = Plane(normal=(0.0, 0.0, 1.0), offset=0.0)
    o = np.array([[0.1, -0.2, 2.0], [0.3, 0.4, 1.0]])
    d = normalize(np.array([[0.0, 0.0, -1.0], [0.2, -0.1, -1.0]]))
    t = -o[:, 2] / d[:, 2]
    r = run(any_backend, "normal", scene, o, d, t_hit=t)
    assert np.all(r.status == Status.CONVERGED)
    np.testing.assert_allclose(r.outputs["normal"], np.tile([0.0, 0.0, 1.0], (2, 1)), rtol=0, atol=1e-12)
    r = run(any_backend, "curvature", scene, o, d, t_hit=t)
    assert np.all(r.status == Status.CONVERGED)
    for key in ("curvature_divergence", "gaussian_curvature", "curvature_laplacian"):
        np.testing.assert_allclose(r.outputs[key], 0.0, rtol=0, atol=tol_for(any_backend, 1e-12, 1e-6))


DT_METHODS = {"dt_implicit": ({}, 1e-12, 1e-8), "dt_idr": ({}, 1e-12, 1e-8),
              "dt_finite_diff": ({"h": 1e-6}, 1e-7, 1e-7), "dt_unrolled": ({"steps": 200}, 1e-9, 1e-5)}


@pytest.mark.parametrize("scene_name", ["sphere", "algebraic"])
@pytest.mark.parametrize("method", sorted(DT_METHODS))
def test_dt_dtheta_against_exact(any_backend, method, scene_name):
    scene = SCENES[scene_name]
    knobs, tol_ad, tol_fd = DT_METHODS[method]
    if method == "dt_unrolled" and scene_name == "algebraic":
        # φ/L steps on |x − c|² − r² contract by ≈ 1 − 2r/L per step, and the derivative of the
        # k-th iterate converges like k·q^k, slower than the iterate: unroll further
        knobs = {"steps": 600}
    o, d, t, hit, x = hits(scene)
    r = run(any_backend, method, scene, o, d, t_hit=None if method == "dt_unrolled" else t, **knobs)
    ok = r.status == Status.CONVERGED
    assert np.all(~ok[~hit]) and ok[hit].mean() >= 0.75, r.status_counts()
    exact = scene.hit_param_grad(o[ok], d[ok], t[ok])
    assert r.outputs["dt_dtheta"].shape == (len(o), scene.param_vector().size)
    err = np.abs(r.outputs["dt_dtheta"][ok] - exact).max()
    assert err <= tol_for(any_backend, tol_ad, tol_fd), err


def test_idr_trick_value_is_a_newton_correction(any_backend):
    o, d, t, hit, x = hits(SPHERE)
    t_off = np.where(hit, t + 1e-4, t)
    r = run(any_backend, "dt_idr", SPHERE, o, d, t_hit=t_off)
    # one Newton step from 1e-4 away lands within O(1e-8) of the hit (quadratic convergence)
    assert np.abs(r.t[hit] - t[hit]).max() <= 1e-6
    assert np.all(np.abs(r.t[hit] - t[hit]) < 1e-4)


def test_grazing_hits_are_flagged_ill_conditioned(any_backend):
    o = np.array([[-3.0, 0.6, 0.05], [-3.0, 0.0, 0.05]])
    o[:, 1] -= 0.2 - 1e-9 * 0  # impact parameters 0.8 (tangent) and 0 (head-on)
    o[0, 1] = 0.8 - 0.2
    d = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    t = np.array([3.1, 3.1 - 0.8])  # tangent point, and the head-on hit
    for method in ("dt_implicit", "dt_idr"):
        r = run(any_backend, method, SPHERE, o, d, t_hit=t, min_cos=1e-6)
        assert r.status[0] == Status.ILL_CONDITIONED and r.status[1] == Status.CONVERGED, r.status


