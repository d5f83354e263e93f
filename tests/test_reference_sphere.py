"""The sphere's exact answers, each checked a second, independent way."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from reference import Sphere, get_case
from reference.quadric import ray_sphere_roots
from reference.rays import normalize

EPS = np.finfo(np.float64).eps


def test_camera_case_hits_are_on_the_surface():
    case = get_case("sphere.camera.64x64")
    t = case.exact_t
    hit = np.isfinite(t)
    assert 0 < hit.sum() < case.n_rays  # some rays hit, some miss
    x = case.origins[hit] + t[hit, None] * case.directions[hit]
    phi = case.scene.value(x)
    assert np.max(np.abs(phi)) <= 4 * EPS * 3  # |x| ≈ 1, a few ulp of the coordinates


def test_misses_really_miss():
    case = get_case("sphere.camera.64x64")
    miss = ~np.isfinite(case.exact_t)
    o, d = case.origins[miss], case.directions[miss]
    # distance from the centre to the ray's line > r  <=> no real root
    b = np.einsum("ij,ij->i", o, d)
    closest = np.linalg.norm(o - b[:, None] * d, axis=1)
    assert np.all(closest > 1.0)


@given(
    k=st.integers(min_value=1, max_value=12),
    sign=st.sampled_from([-1.0, 1.0]),
    dist=st.sampled_from([3.0, 1e3, 1e6]),
    phase=st.floats(0, 2 * np.pi),
)
def test_grazing_and_far_rays_are_cancellation_free(k, sign, dist, phase):
    """Impact parameter 1 ± 10^-k from distance up to 1e6: the float64 roots match a 60-digit
    mpmath evaluation to within backward-stable accuracy, 8·eps·(t + 1/h), where h is the
    half-chord: the depth's own condition number for a perturbation of the impact parameter
    is ℓ/h, so no float64 method can do better.  (The naive b² − ac loses ~eps·t²/h, i.e.
    everything at distance 1e6.)"""
    import mpmath

    mpmath.mp.dps = 60
    b = 1.0 + sign * 10.0 ** (-k)
    side = np.array([np.cos(phase), np.sin(phase), 0.0])
    o = np.array([[0.0, 0.0, dist]]) + b * side
    d = np.array([[0.0, 0.0, -1.0]])
    t0, t1 = ray_sphere_roots(o, d, (0.0, 0.0, 0.0), 1.0)
    ox, oy, oz = (mpmath.mpf(float(v)) for v in o[0])
    impact2 = ox * ox + oy * oy
    if impact2 > 1:
        assert np.isnan(t0[0]) and np.isnan(t1[0])
        return
    h = mpmath.sqrt(1 - impact2)
    exact0, exact1 = oz - h, oz + h
    bound = 8 * EPS * (float(exact1) + 1 / float(h))
    assert abs(t0[0] - float(exact0)) <= bound
    assert abs(t1[0] - float(exact1)) <= bound


def test_origin_inside_hits_the_exit():
    s = Sphere(center=(1.0, 2.0, 3.0), radius=2.0)
    o = np.array([[1.0, 2.0, 3.0]])
    d = normalize(np.array([[1.0, 1.0, 0.0]]))
    assert s.first_hit(o, d)[0] == pytest.approx(2.0, rel=4 * EPS)


def test_normal_matches_central_differences():
    rng = np.random.default_rng(0)
    s = Sphere(center=(0.3, -0.2, 0.1), radius=0.7)
    x = np.asarray(s.center) + 0.7 * normalize(rng.normal(size=(50, 3)))
    h = 1e-6
    grad = np.stack([(s.value(x + h * e) - s.value(x - h * e)) / (2 * h) for e in np.eye(3)], axis=-1)
    np.testing.assert_allclose(s.normal_exact(x), grad, atol=1e-8)
    np.testing.assert_allclose(np.linalg.norm(grad, axis=1), 1.0, atol=1e-8)  # |∇φ| = 1: an SDF


def test_curvature_is_the_textbook_value_and_the_laplacian():
    s = Sphere(radius=2.5)
    x = 2.5 * normalize(np.array([[1.0, 2.0, 2.0]]))
    k1, k2 = s.curvatures_exact(x)
    assert k1[0] == k2[0] == pytest.approx(1 / 2.5)
    # Δφ by second differences equals κ1 + κ2 (the lecture's "mean curvature" for an SDF)
    h = 1e-4
    lap = sum((s.value(x + h * e) - 2 * s.value(x) + s.value(x - h * e)) / h**2 for e in np.eye(3))
    assert lap[0] == pytest.approx(k1[0] + k2[0], rel=1e-6)


def test_hit_param_grad_matches_central_differences_of_the_exact_hit():
    o = np.array([[0.2, 0.1, 4.0]])
    d = normalize(np.array([[0.0, 0.05, -1.0]]))
    s = Sphere(center=(0.1, 0.0, 0.2), radius=1.1)
    t = s.first_hit(o, d)
    g = s.hit_param_grad(o, d, t)[0]
    h = 1e-6
    theta = s.param_vector()
    for i in range(4):
        tp, tm = theta.copy(), theta.copy()
        tp[i] += h
        tm[i] -= h
        fd = (Sphere(tp[:3], tp[3]).first_hit(o, d)[0] - Sphere(tm[:3], tm[3]).first_hit(o, d)[0]) / (2 * h)
        assert g[i] == pytest.approx(fd, abs=1e-7)


def test_bad_parameters_are_named():
    with pytest.raises(ValueError, match="radius"):
        Sphere(radius=-1)
    with pytest.raises(ValueError, match="center"):
        Sphere(center=(0, 0))
