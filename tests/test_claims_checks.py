"""The instruments inside the claim checks, each on a case whose answer is known independently.

These do not assert the lecture's verdicts; they show that each instrument reports a true statement
as true and a false one as false (planted cases), so a verdict it produces can be trusted.
"""

from __future__ import annotations

import mpmath as mp
import numpy as np
import pytest

from bench.claims import LEDGER, run_claims
from bench.claims import _load as load_claims
from bench.claims import adapters
from bench.claims.c01_boolean import exact_csg_sdf
from bench.claims.c06_root_orders import newton, observed_order, secant
from bench.claims.c07_implicit_dt import hit_to_tolerance
from bench.claims.scenes import sphere_dt_truth
from bench.claims.c09_volume_bound import lecture_bound
from bench.claims.rendering import composite, window_samples
from bench.claims.stats import central_laplacian, fit_power
from bench.claims.tracing import sphere_trace_signed
from reference import MLPField, Sphere


def test_fit_power_recovers_planted_rates():
    h = np.logspace(-3, 0, 9)
    assert fit_power(h, 3 * h**2)[0] == pytest.approx(2.0, abs=1e-12)
    assert fit_power(h, 0.1 * h**0.5)[0] == pytest.approx(0.5, abs=1e-12)
    with pytest.raises(ValueError, match="≥ 2"):
        fit_power([1.0], [1.0])


def test_observed_order_tells_orders_apart():
    with mp.workdps(400):
        quad = [mp.mpf(10) ** -(2**k) for k in range(1, 9)]
        golden = [mp.mpf(10) ** -(1.618**k) for k in range(4, 16)]
        lin = [mp.mpf(2) ** -k for k in range(30, 200)]
    assert observed_order(quad) == pytest.approx(2.0, abs=1e-6)
    assert observed_order(golden) == pytest.approx(1.618, abs=1e-3)
    assert observed_order(lin) == pytest.approx(1.0, abs=1e-3)


def test_newton_and_secant_on_sqrt2():
    with mp.workdps(200):
        g = lambda t: t * t - 2  # noqa: E731
        r = mp.sqrt(2)
        en = [abs(x - r) for x in newton(g, lambda t: 2 * t, mp.mpf(1), 10)]
        es = [abs(x - r) for x in secant(g, mp.mpf(1), mp.mpf(2), 14)]
        assert observed_order(en) == pytest.approx(2.0, abs=0.05)
        assert observed_order(es) == pytest.approx((1 + 5**0.5) / 2, abs=0.1)


def test_exact_csg_sdf_against_brute_force():
    """The closed-form CSG distance agrees with the distance to a dense sample of the boundary."""
    from bench.claims.c01_boolean import CA, CB, RA, RB

    rng = np.random.default_rng(0)
    # dense boundary samples of both spheres
    u = rng.normal(size=(200_000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    pa, pb = CA + RA * u, CB + RB * u
    in_b = np.linalg.norm(pa - CB, axis=1) < RB
    in_a = np.linalg.norm(pb - CA, axis=1) < RA
    boundary = {"union": np.concatenate([pa[~in_b], pb[~in_a]]), "intersection": np.concatenate([pa[in_b], pb[in_a]]),
                "difference": np.concatenate([pa[~in_b], pb[in_a]])}
    from scipy.spatial import cKDTree

    x = rng.uniform(-2, 2, (300, 3))
    for op, pts in boundary.items():
        d_brute, _ = cKDTree(pts).query(x)
        sdf, _ = exact_csg_sdf(x, op)
        # the brute force overestimates by at most the sample spacing (~0.01 for 2e5 points on a unit sphere)
        assert np.all(np.abs(sdf) <= d_brute + 1e-12), op
        assert np.max(d_brute - np.abs(sdf)) < 0.02, op


def test_composite_matches_hand_computation_and_rejects_bad_alpha():
    a = np.array([[0.5, 0.5, 1.0]])
    c = np.array([[1.0, 2.0, 4.0]])
    C, T = composite(a, c)
    assert C[0] == pytest.approx(0.5 * 1 + 0.25 * 2 + 0.25 * 4)
    assert T[0] == 0.0
    rgb = np.stack([c, 2 * c, -c], axis=-1)  # channels composite independently with the same weights
    C3, _ = composite(a, rgb)
    assert C3.shape == (1, 3) and np.allclose(C3[0], [C[0], 2 * C[0], -C[0]])
    with pytest.raises(ValueError, match="shapes"):
        composite(a, np.ones((1, 2)))
    with pytest.raises(ValueError, match="alpha"):
        composite(np.array([[1.5]]), np.array([[1.0]]))
    mids, lo, hi, dl = window_samples(np.array([2.0]), 0.5, 4)
    assert np.allclose(mids, [[1.625, 1.875, 2.125, 2.375]]) and np.allclose(dl, 0.25)


def test_lecture_bound_formula():
    g, e, d, n = 2.0, 0.3, 0.5, 3
    a = 0.5 + e * d
    assert lecture_bound(g, e, d, n) == pytest.approx(g * d * abs((2 * e * d - a**n) / (0.5 - e * d)))


def test_density_models_are_opacities():
    phi = np.linspace(-1, 1, 101)[None, :]
    for m in adapters.DENSITY_MODELS:
        a = adapters.density_alphas(m, phi, phi + 0.01, phi - 0.01, np.full(phi.shape, 0.02), 50.0)
        assert np.all((a >= 0) & (a <= 1)), m
    with pytest.raises(ValueError, match="model must be one of"):
        adapters.density_alphas("nope", phi, phi, phi, phi, 1.0)


def test_neus_alpha_deep_inside_is_the_exact_limit():
    """Where Φ_s(sφ) underflows (sφ < −745) the NeuS ratio is 1 − e^{s(φ_end − φ_start)}, not NaN."""
    s = 1000.0
    lo, hi = np.array([-10.0, -0.001]), np.array([-10.001, -0.002])
    a = adapters.density_alphas("neus", lo, lo, hi, np.full(2, 0.001), s)
    assert np.all(np.isfinite(a))
    assert a[0] == pytest.approx(-np.expm1(s * (hi[0] - lo[0])), rel=1e-12)
    sig = lambda z: 1 / (1 + np.exp(-z))  # noqa: E731 - moderate arguments: the plain formula is exact enough
    assert a[1] == pytest.approx((sig(s * lo[1]) - sig(s * hi[1])) / sig(s * lo[1]), rel=1e-12)


def test_tracer_on_the_exact_sphere():
    s = Sphere()
    rng = np.random.default_rng(1)
    d = rng.normal(size=(50, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = -3 * d + 1.5 * rng.uniform(-1, 1, (50, 3))  # some rays miss
    exact = s.first_hit(o, d)
    hit = np.isfinite(exact)
    assert hit.any() and not hit.all()
    r = sphere_trace_signed(s.value, o, d, tol=1e-12)
    assert np.all(r.converged[hit]) and np.max(np.abs(r.t[hit] - exact[hit])) < 1e-9
    assert not np.any(r.converged[~hit])
    # a planted overshooting step (φ/0.4 on an SDF) is caught as passing through
    r2 = sphere_trace_signed(s.value, o, d, lipschitz=0.4, tol=1e-12)
    assert np.any(r2.t_furthest[hit] > exact[hit] + 1e-6)
    with pytest.raises(ValueError, match="lipschitz"):
        sphere_trace_signed(s.value, o, d, lipschitz=0.0)


def test_hit_to_tolerance_and_truth():
    s = Sphere()
    b = np.array([0.0, 0.5, 0.9])
    o = np.stack([b, 0 * b, 3 + 0 * b], -1)
    d = np.tile([0.0, 0.0, -1.0], (3, 1))
    t = hit_to_tolerance(s.value, o, d, np.zeros(3), np.full(3, 3.0), 1e-13)
    assert np.all(np.abs(s.value(o + t[:, None] * d)) <= 1e-13)
    truth, _ = sphere_dt_truth(b)
    assert np.allclose(truth, s.hit_param_grad(o, d, s.first_hit(o, d)), rtol=1e-12, atol=1e-12)


def test_laplacian_stencil_on_a_quadratic():
    x = np.random.default_rng(2).uniform(-1, 1, (10, 3))
    assert np.allclose(central_laplacian(lambda p: np.sum(p * p, -1), x), 6.0, atol=1e-6)


def test_lecture_lipschitz_formula_is_the_reference_bound():
    """The claim's Π‖W_i‖₂ (sup|σ'| = 1) equals the reference MLP's bound, and bounds its gradient."""
    from bench.claims.c04_lipschitz import lipschitz_bound

    net = MLPField()
    L = lipschitz_bound(net)
    assert L == pytest.approx(net.lipschitz_bound, rel=1e-14)
    x = np.random.default_rng(3).uniform(-2, 2, (2000, 3))
    assert np.max(np.linalg.norm(net.jet(x)[1], axis=1)) <= L


def test_interval_membership_tells_the_right_csg_formula_from_a_wrong_one():
    """Signs of min(φ1, φ2) agree with the union's exact ray intervals and disagree with the intersection's."""
    from reference import Intersection, Union

    from bench.claims.c01_boolean import random_ray_points, ray_membership, torus_box_pair

    a, b = torus_box_pair()
    o, d, t, x = random_ray_points(6, 300)
    phi = Union(a, b).value(x)
    for node, expect_agree in ((Union(a, b), True), (Intersection(a, b), False)):
        inside, near = ray_membership(node, o, d, t)
        wrong = np.sum(((phi < 0) != inside) & ~near)
        assert (wrong == 0) == expect_agree, (type(node).__name__, wrong)


def test_csg_distance_bracket_contains_the_closed_form_and_catches_a_wrong_distance():
    """On the sphere pair (closed-form CSG distance known) the certified bracket contains the truth
    everywhere and pins it where it decides; a planted wrong distance (0.9×) falls outside it."""
    from bench.claims.c01_boolean import OPS, sdf_bracket, sphere_pair

    a, b = sphere_pair()
    x = np.random.default_rng(5).uniform(-2.2, 2.2, (20_000, 3))
    for op in OPS:
        sdf, inside = exact_csg_sdf(x, op)
        lo, up, ins = sdf_bracket(op, a, b, x)
        d = np.abs(sdf)
        ok = d > 1e-9
        assert np.array_equal(ins[ok], inside[ok]), op
        assert np.all(lo <= d + 1e-12) and np.all(d <= up + 1e-12), op
        decided = up - lo <= 1e-12 * (1 + lo)
        assert decided.mean() > 0.5, op
        assert np.all(np.abs(d[decided] - lo[decided]) <= 1e-12), op
        wrong = 0.9 * d
        assert np.any(((wrong < lo - 1e-12) | (wrong > up + 1e-12)) & ok), op


def test_ledger_covers_the_lecture_claims():
    load_claims(LEDGER)
    ids = LEDGER.ids()
    for n in range(1, 13):
        assert any(i.rstrip("abc") == str(n) for i in ids), f"claim {n} missing from the ledger"
    for c in LEDGER.select(None):
        assert c.statement and c.equation and c.how_checked, c.id


def test_real_claims_run_without_error(tmp_path):
    """A few cheap real claims produce evidence (not an error row) and their plots."""
    df = run_claims(tmp_path, only=["2c", "3", "4b", "9"])
    assert (df["verdict"] != "error").all(), df[["id", "message"]].to_string()
    assert all((tmp_path / p).stat().st_size > 1000 for p in df["plot"])


@pytest.mark.slow
def test_quick_mode_checks_every_claim_without_error(tmp_path):
    df = run_claims(tmp_path, quick=True)
    assert (df["verdict"] != "error").all(), df[["id", "message"]].to_string()


def test_mesh_distance_instrument_detects_a_wrong_surface():
    """Marching cubes of the unit sphere is within O(h²) of it, and ≈ 0.05 from a sphere of radius 1.05."""
    pytest.importorskip("skimage")
    pytest.importorskip("igl")
    from bench.claims.c12_marching_cubes import mesh_distances

    sph = Sphere()
    rng = np.random.default_rng(4)
    h, haus, cham, _ = mesh_distances(sph, sph.value, "sphere", 32, rng, n_surface=2000)
    assert haus < h**2 and cham < haus
    wrong = Sphere(radius=1.05)
    # distances measured against the wrong exact surface (mesh → surface part) reveal the offset
    _, haus_w, _, _ = mesh_distances(sph, wrong.value, "sphere", 32, rng, n_surface=2000)
    assert haus_w > 0.04
