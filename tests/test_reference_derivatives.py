"""Normals, |∇φ|, curvatures, closest points and dt/dθ, each against an independent computation."""

from __future__ import annotations

import mpmath
import numpy as np
import pytest

from reference.cases import catalog, get_case
from reference.curvature import curvature_sum, gaussian_curvature, mean_curvature
from reference.testing import MP, every_node, to_mp

SCENES = every_node()
EPS = np.finfo(np.float64).eps


def _fd_grad(scene, x, h):
    return np.stack([(scene.value(x + h * e) - scene.value(x - h * e)) / (2 * h) for e in np.eye(3)], axis=-1)


@pytest.mark.parametrize("name", sorted(SCENES))
def test_jet_gradient_matches_central_differences(name):
    """∇φ of the jet against central differences at random points; points near a kink (where
    differences with h and 4h disagree) are excluded — they are where ∇φ is undefined."""
    scene = SCENES[name]
    x = np.random.default_rng(3).uniform(-1.5, 1.5, size=(400, 3))
    g1, g4 = _fd_grad(scene, x, 1e-6), _fd_grad(scene, x, 4e-6)
    smooth = np.max(np.abs(g1 - g4), axis=1) < 1e-7
    assert smooth.mean() > 0.9
    _, g, _ = scene.jet(x)
    np.testing.assert_allclose(g[smooth], g1[smooth], atol=1e-7)
    if scene.info.exact_sdf:  # |∇φ| = 1 away from the medial axis
        np.testing.assert_allclose(np.linalg.norm(g1[smooth], axis=1), 1.0, atol=1e-7)


@pytest.mark.parametrize("name", sorted(SCENES))
def test_jet_param_partials_match_central_differences(name):
    scene = SCENES[name]
    x = np.random.default_rng(4).uniform(-1.5, 1.5, size=(200, 3))
    theta = scene.param_vector()
    _, _, dth = scene.jet(x)
    h = 1e-6
    ok_total = 0
    for i in range(theta.size):
        tp, tm = theta.copy(), theta.copy()
        tp[i] += h
        tm[i] -= h
        fd = (scene.with_params(tp).value(x) - scene.with_params(tm).value(x)) / (2 * h)
        tp[i] += 3 * h
        tm[i] -= 3 * h
        fd4 = (scene.with_params(tp).value(x) - scene.with_params(tm).value(x)) / (8 * h)
        smooth = np.abs(fd - fd4) < 1e-7
        ok_total += smooth.sum()
        np.testing.assert_allclose(dth[smooth, i], fd[smooth], atol=1e-7)
    assert ok_total >= 0.9 * theta.size * x.shape[0]


def _mp_grad_hess(scene, x, h=mpmath.mpf("1e-15")):
    """∇φ and Hessian by central differences on the mpmath evaluation at 50 digits
    (truncation O(h²) ≈ 1e-30, rounding 1e-50/h² ≈ 1e-20: both far below float64)."""
    mpmath.mp.dps = 50
    xm = to_mp(x)
    n = x.shape[0]
    E = np.eye(3, dtype=object)
    f = lambda y: MP.asarray(scene.value(y, MP))
    f0 = f(xm)
    g = np.zeros((n, 3))
    H = np.zeros((n, 3, 3))
    for i in range(3):
        fp, fm = f(xm + h * E[i]), f(xm - h * E[i])
        g[:, i] = [float(v) for v in (fp - fm) / (2 * h)]
        H[:, i, i] = [float(v) for v in (fp - 2 * f0 + fm) / h**2]
        for j in range(i + 1, 3):
            fpp, fpm = f(xm + h * E[i] + h * E[j]), f(xm + h * E[i] - h * E[j])
            fmp, fmm = f(xm - h * E[i] + h * E[j]), f(xm - h * E[i] - h * E[j])
            H[:, i, j] = H[:, j, i] = [float(v) for v in (fpp - fpm - fmp + fmm) / (4 * h * h)]
    return g, H


# neural.blob.camera.16x16.Llocal is left out: the same network and the same hits as
# neural.blob.camera.16x16 (only the declared Lipschitz bound differs), and its 50-digit
# evaluation costs ~20 s a case.
CURV_CASES = [c.id for c in catalog() if c.scene.info.exact_curvature and "camera" in c.tags
              and "scale" not in c.tags and "thin" not in c.tags and c.id != "neural.blob.camera.16x16.Llocal"]


@pytest.mark.slow  # compiles many kernels or sweeps a whole catalog
@pytest.mark.parametrize("cid", CURV_CASES)
def test_curvatures_against_mpmath_finite_differences(cid):
    """κ1 + κ2 and κ1κ2 from the closed form against the implicit-surface formulas applied to a
    50-digit finite-difference gradient g and Hessian H (Goldman 2005, independent of
    :func:`principal_from_hessian`):  κ1 + κ2 = (|g|² tr H − gᵀHg)/|g|³,
    κ1κ2 = −det[[H, g], [gᵀ, 0]]/|g|⁴.  Points on edges (NaN) are skipped."""
    case = get_case(cid)
    rng = np.random.default_rng(5)
    hits = np.flatnonzero(case.hit_mask)
    # 12 points on the neural SDF, whose 4481 weights take ~1.3 s a point at 50 digits
    idx = rng.choice(hits, size=min(12 if "neural" in case.tags else 24, hits.size), replace=False)
    x = case.exact_points[idx]
    k1, k2 = case.exact_curvatures[0][idx], case.exact_curvatures[1][idx]
    ok = np.isfinite(k1)
    assert ok.sum() >= 8
    x, k1, k2 = x[ok], k1[ok], k2[ok]
    g, H = _mp_grad_hess(case.scene, x)
    gn = np.linalg.norm(g, axis=1)
    ksum = (gn**2 * np.trace(H, axis1=1, axis2=2) - np.einsum("ni,nij,nj->n", g, H, g)) / gn**3
    bordered = np.zeros((x.shape[0], 4, 4))
    bordered[:, :3, :3], bordered[:, :3, 3], bordered[:, 3, :3] = H, g, g
    kgauss = -np.linalg.det(bordered) / gn**4
    assert np.all(k1 >= k2)
    np.testing.assert_allclose(curvature_sum(k1, k2), ksum, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(gaussian_curvature(k1, k2), kgauss, rtol=1e-9, atol=1e-9)


def test_curvature_helpers_and_sign_convention():
    s = get_case("sphere.camera.64x64").scene
    k1, k2 = s.curvatures_exact(np.array([[0.0, 0.0, 1.0]]))
    assert mean_curvature(k1, k2)[0] == 1.0 and curvature_sum(k1, k2)[0] == 2.0 and gaussian_curvature(k1, k2)[0] == 1.0
    t = SCENES["scaled"].child  # torus R = 1, r = 0.25: inner equator is a saddle with κ2 = −1/(R − r)
    k1, k2 = t.curvatures_exact(np.array([[0.75, 0.0, 0.0], [1.25, 0.0, 0.0]]))
    np.testing.assert_allclose(k1, [4.0, 4.0])
    np.testing.assert_allclose(k2, [-1 / 0.75, 1 / 1.25])
    c1, c2 = SCENES["complement"].curvatures_exact(np.array([[1.0, 0.0, 0.0]]))
    assert c1[0] == -1.0 and c2[0] == -1.0


def test_laplacian_is_the_curvature_sum_only_for_sdfs():
    """Δφ = κ1 + κ2 on an SDF's surface, but the algebraic sphere |x|² − r² has Δφ = 6 ≠ 2/r
    (its curvature sum is div(∇φ/|∇φ|) = 2/r)."""
    x = np.array([[0.0, 0.6, 0.8]])
    for scene, lap in ((get_case("sphere.camera.64x64").scene, 2.0), (SCENES["algsphere"], 6.0)):
        _, H = _mp_grad_hess(scene, x if scene.kind == "sphere" else np.asarray(scene.center) + 0.9 * x)
        assert np.trace(H[0]) == pytest.approx(lap, rel=1e-12)


@pytest.mark.parametrize("name", [n for n in sorted(SCENES) if SCENES[n].info.exact_sdf])
def test_closest_point_is_on_the_surface_at_distance_phi(name):
    """x* = x − φ∇φ: φ(x*) = 0 and |x − x*| = |φ(x)| — together they say x* is a closest
    point (the distance to the surface of an exact SDF is |φ|)."""
    scene = SCENES[name]
    x = np.random.default_rng(6).uniform(-1.5, 1.5, size=(300, 3))
    cp = scene.closest_point_exact(x)
    phi = scene.value(x)
    np.testing.assert_allclose(scene.value(cp), 0.0, atol=64 * EPS)
    np.testing.assert_allclose(np.linalg.norm(x - cp, axis=1), np.abs(phi), atol=64 * EPS)


def test_closest_point_refuses_non_sdfs():
    with pytest.raises(ValueError, match="not an exact SDF"):
        SCENES["algsphere"].closest_point_exact(np.zeros((1, 3)))


# The neural SDF's cases are left out: differencing all 4481 of its weights means ~18 000 numerical
# hits (tens of minutes); tests/test_neural_reference.py checks its dt/dθ on a sample of weights
# from every layer against differences of independently bracketed hits.
DT_CASES = [c.id for c in catalog() if c.scene.info.exact_hit_param_grad and c.scene.param_vector().size
            and ("camera" in c.tags or "inside" in c.tags) and "scale" not in c.tags and "thin" not in c.tags
            and "neural" not in c.tags]


#: parameters differenced per parameter array (``W1``, ``b1``, …) of a scene with many: every
#: array, so every layer's term of the chain rule, is checked (the MLP: 48 of its 353 weights,
#: 9 s instead of 39 s; each difference is 4 numerical hits)
PER_ARRAY = 8


def _params_to_difference(names: list[str]) -> list[int]:
    """Indices of the parameters to difference: all of an array of ≤ :data:`PER_ARRAY`, else
    :data:`PER_ARRAY` of it drawn at random (seeded), its first and last among them."""
    arrays: dict[str, list[int]] = {}
    for i, name in enumerate(names):
        arrays.setdefault(name.split("[")[0], []).append(i)
    rng = np.random.default_rng(11)
    picked = []
    for idx in arrays.values():
        if len(idx) <= PER_ARRAY:
            picked += idx
        else:
            picked += [idx[0], idx[-1], *rng.choice(idx[1:-1], PER_ARRAY - 2, replace=False).tolist()]
    return sorted(picked)


@pytest.mark.slow  # compiles many kernels or sweeps a whole catalog
@pytest.mark.parametrize("cid", DT_CASES)
def test_dt_dtheta_matches_central_differences_of_the_exact_hit(cid):
    """dt/dθ (implicit differentiation with closed-form partials) against (t(θ + h) − t(θ − h))/2h
    of the exact hit, h = 1e-6, on rays that cross at |n·d| ≥ 0.1 (elsewhere dt/dθ is large and
    its differences ill-conditioned) and away from CSG seams (the active child must not change)."""
    case = get_case(cid)
    scene = case.scene
    hits = np.flatnonzero(case.hit_mask)
    x = case.exact_points[hits]
    cos = np.abs(np.einsum("ij,ij->i", scene.normal_exact(x), case.directions[hits]))
    idx = np.random.default_rng(7).choice(hits[cos >= 0.1], size=min(24, int((cos >= 0.1).sum())), replace=False)
    o, d = case.origins[idx], case.directions[idx]
    g = case.exact_dt_dtheta[idx]
    theta = scene.param_vector()
    h = 1e-6
    for i in _params_to_difference(scene.param_names()):
        tp, tm = theta.copy(), theta.copy()
        tp[i] += h
        tm[i] -= h
        fd = (scene.with_params(tp).first_hit(o, d, case.t_min) - scene.with_params(tm).first_hit(o, d, case.t_min)) / (2 * h)
        tp[i] += h
        tm[i] -= h
        fd2 = (scene.with_params(tp).first_hit(o, d, case.t_min) - scene.with_params(tm).first_hit(o, d, case.t_min)) / (4 * h)
        same = np.abs(fd - fd2) < 1e-6  # the active CSG child did not switch within ±2h
        assert same.mean() >= 0.75
        err = np.abs(g[same, i] - fd[same]) / (1 + np.abs(fd[same]))
        assert np.all(err <= 1e-6), (scene.param_names()[i], float(np.max(err)))
