"""The numerical reference (certified bracketing + bisection), the MLP field and user callables."""

from __future__ import annotations

import numpy as np
import pytest

from reference.cases import get_case, wavy_sphere
from reference.mlp import MLPField
from reference.numerical import CallableField, crossings_numeric, first_hit_numeric

EPS = np.finfo(np.float64).eps


@pytest.mark.parametrize("cid", ["torus.camera.32x32", "csg.union.camera.32x32", "torus.grazing.1e-6",
                                 "csg.shell.1e-4", "ellipsoid.camera.32x32"])
def test_numerical_reference_agrees_with_closed_forms(cid):
    """Same hit/miss on every ray, and both depths within their stated bounds of the same real
    root: |t_numerical − t_closed| ≤ err_numerical + err_closed (reference.depthbound); the
    stated bound is at least the bisection bracket and, off tangency, of the order of φ's rounding
    over the slope, 16ε·(|o|₁ + t + m)/|∂φ/∂t| (twice it at most, from the doubling search)."""
    case = get_case(cid)
    t, err = first_hit_numeric(case.scene, case.origins, case.directions, case.t_min, case.t_max)
    ex = case.exact_t
    assert np.array_equal(np.isfinite(t), np.isfinite(ex))
    m = np.isfinite(ex)
    assert case.judged_mask.all() and np.all(np.isfinite(err))
    assert np.all(np.abs(t[m] - ex[m]) <= err[m] + case.exact_t_error_bounds[m])
    _, g, _ = case.scene.jet(case.exact_points[m])
    slope = np.abs(np.einsum("ij,ij->i", g, case.directions[m]))
    from reference.depthbound import magnitude, rounding_gain

    L = case.scene.info.lipschitz
    first_order = 16 * EPS * rounding_gain(case.scene) * L * (ex[m] + magnitude(case.scene, case.origins[m])) / slope
    steep = slope > 0.1 * L
    assert np.all(err[m] >= np.spacing(ex[m]))
    assert np.all(err[m][steep] <= 4 * first_order[steep] + 4 * np.spacing(ex[m][steep]))


def test_certification_finds_short_intervals_that_sampling_alone_misses():
    """Grazing torus hits at 1e-6 have chords ~3e-3 < the 6e-3 sample spacing: without a
    Lipschitz bound some are missed; with the certified refinement none are."""
    case = get_case("torus.grazing.1e-6")
    t_plain, _ = first_hit_numeric(case.scene, case.origins, case.directions, 0.0, 6.0, lipschitz=None, n_samples=1000)
    t_cert, _ = first_hit_numeric(case.scene, case.origins, case.directions, 0.0, 6.0, n_samples=1000)
    assert np.isfinite(t_plain).sum() < case.hit_mask.sum()
    np.testing.assert_array_equal(np.isfinite(t_cert), case.hit_mask)


def test_crossings_numeric_lists_every_boundary():
    case = get_case("csg.union.camera.32x32")
    idx = np.arange(0, case.n_rays, 7)
    cr, _ = crossings_numeric(case.scene, case.origins[idx], case.directions[idx], case.t_min, case.t_max)
    exact = case.scene.ray_intervals(case.origins[idx], case.directions[idx])
    for a, b in zip(cr, exact):
        b = b[(b > case.t_min) & (b < case.t_max)]
        assert a.shape == b.shape
        np.testing.assert_allclose(a, b, atol=1e-12)


def test_mlp_hits_bracket_a_sign_change():
    case = get_case("mlp.camera.32x32")
    m = case.hit_mask
    assert 50 < m.sum() < case.n_rays
    t = case.exact_t[m]
    # the stated depth bound (reference.depthbound) covers at least the bisection bracket and is
    # the rounding of φ (16ε·L·(|t| + m), L ≈ 29.9) over slopes of order 1: no ray flagged
    b = case.exact_t_error_bounds[m]
    assert case.judged_mask.all() and np.all(b >= np.spacing(t)) and case.exact_t_error_bound <= 1e-11
    o, d = case.origins[m], case.directions[m]
    ulp = np.spacing(t)
    f_before = case.scene.value(o + (t - 2 * ulp)[:, None] * d)
    f_after = case.scene.value(o + (t + 2 * ulp)[:, None] * d)
    assert np.all(np.sign(f_before) != np.sign(f_after)) or np.all(np.abs(case.scene.value(case.exact_points[m])) < 1e-14)
    assert np.all(case.scene.value(o) > 0)  # the camera is outside, so the first crossing enters


def test_mlp_lipschitz_bound_is_the_product_of_spectral_norms_and_holds():
    """L = Π‖Wᵢ‖₂ (sup|σ'| = 1): spectral norms checked by power iteration (independent of
    SVD), and empirical difference quotients never exceed L."""
    mlp = MLPField()
    rng = np.random.default_rng(0)
    prod = 1.0
    for k in ("W1", "W2", "W3"):
        W = mlp.weights[k]
        v = rng.normal(size=W.shape[1])
        for _ in range(2000):
            v = W.T @ (W @ v)
            v /= np.linalg.norm(v)
        prod *= np.linalg.norm(W @ v)
    assert mlp.lipschitz_bound == pytest.approx(prod, rel=1e-10)
    x = rng.uniform(-3, 3, size=(20000, 3))
    y = x + rng.normal(size=x.shape) * rng.uniform(1e-4, 1.0, size=(20000, 1))
    q = np.abs(mlp.value(x) - mlp.value(y)) / np.linalg.norm(x - y, axis=1)
    assert q.max() <= mlp.lipschitz_bound


def test_mlp_is_bit_identical_in_jax_eager_and_within_a_few_ulp_elsewhere():
    """Measured: jax eager reproduces numpy bit for bit; torch and jax.jit sum the matmuls in a
    different order (or fused), differing by up to 2.9 (torch) and 4.3 (jax.jit) ulp of max|φ|
    (≈ 1.1e-15 absolute) on this machine; the test allows 8 ulp so another CPU's SIMD width
    does not fail it."""
    torch = pytest.importorskip("torch")
    jax = pytest.importorskip("jax")
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    from array_api_compat import torch as xpt

    mlp = MLPField()
    x = np.random.default_rng(1).uniform(-2, 2, size=(4096, 3))
    ref = mlp.value(x)
    np.testing.assert_array_equal(np.asarray(mlp.value(jnp.asarray(x), jnp)), ref)
    scale = np.max(np.abs(ref))
    for out in (mlp.value(torch.from_numpy(x), xpt).numpy(), np.asarray(jax.jit(lambda p: mlp.value(p, jnp))(jnp.asarray(x)))):
        assert np.max(np.abs(out - ref)) <= 8 * EPS * scale


def test_mlp_dt_dtheta_matches_differences_of_the_numerical_hit():
    case = get_case("mlp.camera.32x32")
    mlp = case.scene
    hits = np.flatnonzero(case.hit_mask)
    x = case.exact_points[hits]
    cos = np.abs(np.einsum("ij,ij->i", mlp.normal_exact(x), case.directions[hits]))
    idx = hits[cos > 0.3][:8]
    o, d = case.origins[idx], case.directions[idx]
    g = case.exact_dt_dtheta[idx]
    theta = mlp.param_vector()
    h = 1e-6
    for i in np.random.default_rng(2).choice(theta.size, size=12, replace=False):
        tp, tm = theta.copy(), theta.copy()
        tp[i] += h
        tm[i] -= h
        fd = (first_hit_numeric(mlp.with_params(tp), o, d, 0.0, 6.0)[0] - first_hit_numeric(mlp.with_params(tm), o, d, 0.0, 6.0)[0]) / (2 * h)
        np.testing.assert_allclose(g[:, i], fd, atol=1e-7, err_msg=mlp.param_names()[i])


def test_callable_field_states_what_it_is_told():
    f = CallableField(wavy_sphere, lipschitz=1.25, name="wavy")
    assert f.info.lipschitz == 1.25 and not f.info.exact_hits and not f.info.exact_sdf
    case = get_case("callable.wavy.camera.32x32")
    # the bound is valid: no difference quotient exceeds it
    rng = np.random.default_rng(3)
    x = rng.uniform(-2, 2, size=(20000, 3))
    y = x + 1e-3 * rng.normal(size=x.shape)
    q = np.abs(f.value(x) - f.value(y)) / np.linalg.norm(x - y, axis=1)
    assert q.max() <= 1.25
    assert case.hit_mask.sum() > 500
    with pytest.raises(ValueError, match="lipschitz"):
        CallableField(wavy_sphere, lipschitz=-1.0)
    with pytest.raises(ValueError, match="callable"):
        CallableField(3.0)
    with pytest.raises(ValueError, match="t_max"):
        first_hit_numeric(f, np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), 0.0, np.inf)
    with pytest.raises(ValueError, match="no closed-form"):
        case.exact_dt_dtheta


@pytest.mark.parametrize("steep", [1.0, 4.0])
def test_rays_taken_in_passes_give_the_answers_of_one_pass(monkeypatch, steep):
    """The numerical reference takes rays CHUNK_RAYS at a time (its dense samples made a user's
    256² camera take 4.7 GB in one pass, 1024² ~80 GB); passes give bit for bit what one pass
    gives: hits, misses, the error bounds and every crossing, and, where the bound is understated
    on part of the field (``steep`` 4), every ray voided, the refutation seen in one pass voiding
    the rays of the others (:func:`reference.numerical._void_if_refuted`)."""
    from reference import numerical as N
    from reference import rays

    def field(x, xp):  # a ball and a slab `steep` × the declared L = 1
        r = xp.sqrt(xp.sum(x * x, axis=-1)) - 0.5
        return xp.minimum(r, steep * (xp.abs(x[..., 1] - 0.4) - 0.05))

    scene = CallableField(field, lipschitz=1.0, name=f"tests.ball_and_slab_{steep:g}")
    o, d = rays.pinhole(eye=(0.3, 0.2, 3.0), look_at=(0.3, 0.0, 0.0), fov_deg=50.0, width=24, height=24)
    one = N.first_hit_numeric(scene, o, d, 0.0, 6.0), N.crossings_numeric(scene, o, d, 0.0, 6.0)
    monkeypatch.setattr(N, "CHUNK_RAYS", 100)
    many = N.first_hit_numeric(scene, o, d, 0.0, 6.0), N.crossings_numeric(scene, o, d, 0.0, 6.0)
    t, err = one[0]
    if steep > 1.0:
        assert np.all(np.isnan(t)) and np.all(err == np.inf) and np.all(one[1][1] == np.inf)
    else:
        assert np.isfinite(t).any() and np.isinf(t).any() and not np.isnan(t).any()  # hits and misses
    for a, b in zip(one[0], many[0]):
        np.testing.assert_array_equal(a, b)
    assert len(one[1][0]) == len(many[1][0]) == len(o)
    for a, b in zip(one[1][0], many[1][0]):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(one[1][1], many[1][1])


def test_directions_that_are_not_unit_are_refused_and_float32_ones_are_normalised_again():
    """The scan's Lipschitz checks and exclusions are in t, where φ(o + t d) is L·‖d‖-Lipschitz:
    ‖d‖ = 3 was accepted and flagged every ray of a thin shell.  Now it is refused by name, with
    the fix; directions normalised in float32 (‖d‖ − 1 up to ~1e-7) are accepted and, as the
    backends do (impls.base.check_rays), normalised again in float64: the depths are those of
    d/‖d‖, and the caller's array is not written."""
    scene = get_case("csg.shell.1e-4").scene
    rng = np.random.default_rng(4)
    o = rng.normal(size=(64, 3))
    o = 3.0 * o / np.linalg.norm(o, axis=1, keepdims=True)
    d = rng.uniform(-0.5, 0.5, (64, 3)) - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    for fn in (first_hit_numeric, crossings_numeric):
        with pytest.raises(ValueError, match=r"d must be unit vectors .*\(ray \d+\) has ‖d‖ − 1 = 2\.000e\+00.*Normalise"):
            fn(scene, o, 3.0 * d, 0.0, 2.0)
    d32 = d.astype(np.float32)
    d32 = d32 / np.linalg.norm(d32, axis=1, keepdims=True)
    kept = d32.copy()
    t32, _ = first_hit_numeric(scene, o, d32, 0.0, 6.0)
    np.testing.assert_array_equal(d32, kept)
    with pytest.raises(ValueError, match="float64 directions"):  # the same values in float64: float64's tolerance
        first_hit_numeric(scene, o, d32.astype(np.float64), 0.0, 6.0)
    d32_64 = d32.astype(np.float64)
    t64, _ = first_hit_numeric(scene, o, d32_64 / np.linalg.norm(d32_64, axis=1, keepdims=True), 0.0, 6.0)
    assert np.isfinite(t64).sum() > 20
    np.testing.assert_array_equal(t32, t64)


def test_a_bound_refuted_on_one_ray_voids_every_rays_answer():
    """A thin steep wall (slope 1000) in front of the unit sphere, declared L = 1: the scan sees the
    false bound only on the rays whose samples straddle the wall's slope.  Before, only those were
    voided, and 60 of 256 rays kept the sphere behind the wall as their "first hit" (judged, so a
    root finder stepping over the wall the same way scored 0 false hits); L is one claim about the
    field, so every ray is now without an answer (t NaN, bound inf), as the backends void theirs."""
    from reference.rays import pinhole

    def wall(x, xp):
        r = xp.sqrt(xp.sum(x * x, axis=-1))
        return xp.minimum(r - 1.0, 1000.0 * (xp.abs(r - 2.3) - 5e-4))

    o, d = pinhole((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), fov_deg=40, width=16, height=16)
    field = CallableField(wall, lipschitz=1.0, name="tests.wall")
    t, err = first_hit_numeric(field, o, d, 0.0, 6.0)
    assert np.all(np.isnan(t)) and np.all(err == np.inf), (int(np.isfinite(t).sum()), int(np.isnan(t).sum()))
    per_ray = [first_hit_numeric(field, o[k:k + 1], d[k:k + 1], 0.0, 6.0)[0][0] for k in range(0, 256, 17)]
    assert any(np.isfinite(per_ray)), "some rays alone do not see the refutation (what made this a finding)"
    _, width = crossings_numeric(field, o, d, 0.0, 6.0)
    assert np.all(width == np.inf)


def test_a_field_that_is_nan_somewhere_is_named_with_a_point():
    """Before: "the field returned non-finite values on the rays", naming neither the field nor
    where (the 2026-11-30 probe).  Now the field, the value, a point, its ray and depth."""
    from reference.rays import pinhole

    f = CallableField(lambda x, xp: xp.where(x[..., 0] > 0.3, xp.nan, xp.sqrt(xp.sum(x * x, axis=-1)) - 1.0),
                      lipschitz=1.0, name="tests.nan_beyond")
    o, d = pinhole((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), width=8, height=8)
    with pytest.raises(ValueError, match=r"'tests.nan_beyond' \(CallableField\) returned nan at x = \[0\.3.*\(ray \d+, "
                                         r"t = .*rays meet such points"):
        first_hit_numeric(f, o, d, 0.0, 6.0)


def test_a_users_bounding_ball_that_leaves_out_the_surface_is_refuted():
    """``CallableField(bounds=…, domain=…)``: the search keeps to the ray bounds of the ball the
    user asserts holds every point where φ ≤ 0.  A ball that leaves out the unit sphere made every
    ray a certified MISS, judged right (the 2026-11-30 probe); now the stretches it leaves out are
    sampled, φ ≤ 0 there refutes it, and no ray has an answer.  A true ball changes nothing."""
    from reference.rays import pinhole

    def sphere(x, xp):
        return xp.sqrt(xp.sum(x * x, axis=-1)) - 1.0

    o, d = pinhole((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), fov_deg=40, width=16, height=16)
    wrong = CallableField(sphere, lipschitz=1.0, name="tests.wrong_ball", bounds=((5.0, 5.0, 5.0), 0.5), domain="ball")
    t, err = first_hit_numeric(wrong, o, d, 0.0, 6.0)
    assert np.all(np.isnan(t)) and np.all(err == np.inf)
    right = CallableField(sphere, lipschitz=1.0, name="tests.right_ball", bounds=((0.0, 0.0, 0.0), 1.01),
                          domain="ball")
    t, err = first_hit_numeric(right, o, d, 0.0, 6.0)
    assert np.isfinite(t).sum() > 100 and np.isinf(t).sum() > 0 and not np.isnan(t).any()
