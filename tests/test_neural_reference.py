"""The trained neural SDF (reference.neural): evaluation on every library, its derivatives, its
certified bounds and ray bounds, and its hits against an independent root finder."""

from __future__ import annotations

import importlib

import numpy as np
import pytest

from reference import first_hit_numeric, get_case
from reference.neural import CERT_KEYS, NeuralSDF, certify, measure_slope

neural_cases = importlib.import_module("reference.neural_cases")  # the package re-exports a function of that name

EPS = np.finfo(np.float64).eps


@pytest.fixture(scope="module")
def net():
    return neural_cases.stored_network("spectral")


def _points(n, seed, pad=0.3):
    net = neural_cases.stored_network("spectral")
    return np.random.default_rng(seed).uniform(net.domain_lo - pad, net.domain_hi + pad, size=(n, 3))


# -- evaluation --------------------------------------------------------------------------------


def test_numpy_torch_and_jax_agree_to_float64_rounding(net):
    """The same formula in every library: only exp/log1p (libm, SLEEF, XLA) and the matmul's
    summation order differ, a few ε of φ's magnitude (1 + |φ|)."""
    torch = pytest.importorskip("torch")
    jax = pytest.importorskip("jax")
    import array_api_compat.torch as xpt
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    x = _points(3000, 1)
    ref = net.value(x)
    outs = {"torch": net.value(torch.from_numpy(x), xpt).numpy(),
            "jax": np.asarray(net.value(jnp.asarray(x), jnp)),
            "jax.jit": np.asarray(jax.jit(lambda p: net.value(p, jnp))(jnp.asarray(x)))}
    for name, out in outs.items():
        assert out.dtype == np.float64
        err = np.max(np.abs(out - ref) / (1 + np.abs(ref)))
        assert err <= 8 * EPS, (name, err)


def test_theta_round_trip_and_theta_argument(net):
    theta = net.param_vector()
    assert theta.size == len(net.param_names()) == 3 * 64 + 64 + 64 * 64 + 64 + 64 + 1
    again = net.with_params(theta)
    x = _points(500, 2)
    np.testing.assert_array_equal(again.value(x), net.value(x))
    np.testing.assert_array_equal(net.value(x, np, theta), net.value(x))
    assert again.content_hash() == net.content_hash()
    moved = theta.copy()
    moved[-1] += 0.25  # the output bias: φ moves by exactly 0.25
    np.testing.assert_allclose(net.with_params(moved).value(x), net.value(x) + 0.25, atol=4 * EPS)


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="lipschitz must be one of"):
        NeuralSDF(lipschitz="tight")
    with pytest.raises(ValueError, match="not found"):
        NeuralSDF("/nonexistent/weights.npz")
    w = neural_cases.stored_network().own_params() | {"beta": 100.0, "domain_lo": -np.ones(3), "domain_hi": np.ones(3)}
    with pytest.raises(ValueError, match="do not chain"):
        NeuralSDF(weights=w | {"W2": np.zeros((63, 64))})


def test_jet_and_hessian_against_autodiff_and_differences(net):
    """∇φ, ∂φ/∂θ and the Hessian in closed form against torch autograd (to rounding), and ∇φ
    against central differences (h = 1e-6: truncation ~h²|φ'''| with |φ'''| up to ~β²)."""
    torch = pytest.importorskip("torch")
    import array_api_compat.torch as xpt

    x = _points(200, 3)
    phi, g, dth = net.jet(x)
    _, g2, H = net.gradient_hessian(x)
    np.testing.assert_allclose(g2, g, atol=1e-14)
    xt = torch.from_numpy(x).requires_grad_()
    (gt,) = torch.autograd.grad(net.value(xt, xpt).sum(), xt)
    np.testing.assert_allclose(g, gt.numpy(), atol=1e-13)
    th = torch.from_numpy(net.param_vector()).requires_grad_()
    jac = torch.autograd.functional.jacobian(lambda t: net.value(torch.from_numpy(x[:20]), xpt, t), th)
    np.testing.assert_allclose(dth[:20], jac.numpy(), atol=1e-13)
    Ht = torch.autograd.functional.hessian(lambda p: net.value(p[None], xpt)[0], torch.from_numpy(x[5]))
    np.testing.assert_allclose(H[5], Ht.numpy(), rtol=1e-11, atol=1e-11)
    h = 1e-6
    fd = np.stack([(net.value(x + h * e) - net.value(x - h * e)) / (2 * h) for e in np.eye(3)], axis=-1)
    assert np.max(np.abs(fd - g)) < 1e-6


# -- certificates --------------------------------------------------------------------------------


def test_stored_certificate_is_reproduced_and_the_local_bound_holds(net):
    """The certificate stored with the weights is what :func:`certify` computes from them; the
    local bound lies between the largest slope found by an independent search (more samples, a
    different seed, local maximisation) and the spectral bound; the surface box lies in the
    domain and φ > 0 at sampled points outside it, near and far."""
    fresh = certify(NeuralSDF(weights={**net.own_params(), "beta": net.beta, "domain_lo": net.domain_lo,
                                       "domain_hi": net.domain_hi}))
    for k in CERT_KEYS:
        np.testing.assert_allclose(np.asarray(fresh[k], np.float64), np.asarray(net.certificate[k], np.float64),
                                   rtol=1e-12, err_msg=k)
    lo, hi = net.local_box
    found = measure_slope(net, lo, hi, samples=60_000, starts=10, seed=7)
    assert found <= net.local_bound < net.spectral_bound
    assert net.measured_slope <= net.local_bound
    blo, bhi = net.surface_box
    assert np.all(net.domain_lo < blo) and np.all(bhi < net.domain_hi)
    assert np.all(lo <= blo) and np.all(bhi <= hi)
    rng = np.random.default_rng(8)
    x = np.concatenate([rng.uniform(net.domain_lo - 2, net.domain_hi + 2, size=(40_000, 3)),
                        rng.normal(size=(2000, 3)) * 1e6])
    outside = np.any((x < blo) | (x > bhi), axis=1)
    assert outside.sum() > 30_000 and np.all(net.value(x[outside]) > 0)


def test_modes_state_their_bound_and_domain(net):
    local, measured = net.with_lipschitz("local"), net.with_lipschitz("measured")
    assert net.info.lipschitz == net.spectral_bound and net.info.domain is None
    assert local.info.lipschitz == net.local_bound and measured.info.lipschitz == pytest.approx(1.05 * net.measured_slope)
    assert local.info.domain == measured.info.domain and local.info.domain.startswith("box (")
    # the ray bounds (where the root finders search) lie in the local box, where L holds
    case = get_case("neural.blob.camera.16x16")
    lo_t, hi_t = local.ray_bounds(np, case.origins, case.directions)
    ok = lo_t <= hi_t
    assert ok.sum() > 100
    blo, bhi = local.local_box
    for t in (lo_t[ok], hi_t[ok]):
        p = case.origins[ok] + t[:, None] * case.directions[ok]
        assert np.all((p >= blo) & (p <= bhi))


# -- hits ------------------------------------------------------------------------------------


def _brentq_first_hits(scene, o, d, t_min, t_max, n=4001):
    """First sign change on a dense grid of ``n`` depths (not the reference's), then scipy's
    brentq to xtol 1e-14: an independent root finder (uncertified: it can miss what falls
    between its samples)."""
    from scipy.optimize import brentq

    ts = np.linspace(t_min, t_max, n)
    f = scene.value(o[:, None, :] + ts[None, :, None] * d[:, None, :])
    out = np.full(o.shape[0], np.inf)
    for i in range(o.shape[0]):
        j = np.flatnonzero((f[i, 1:] > 0) != (f[i, :-1] > 0))
        if j.size:
            a, b = ts[j[0]], ts[j[0] + 1]
            out[i] = brentq(lambda t: float(scene.value(o[i] + t * d[i])), a, b, xtol=1e-14, rtol=4 * EPS)
    return out


@pytest.mark.parametrize("cid", ["neural.blob.camera.16x16", "neural.blob.camera.16x16.Llocal",
                                 "neural.blob.grazing.1e-3.Llocal"])
def test_hits_bracket_a_sign_change_and_agree_with_brentq(cid):
    """The reference's hits lie on the surface (the float64 φ changes sign within 4 ulp of t, its
    error bound being ≤ 2 ulp) and agree with brentq on an independent grid to ~1e-14 (the float64
    φ is noisy at ~1e-16 around its zero, so two certified roots can differ by that over |dφ/dt|);
    both find the same rays' hits."""
    case = get_case(cid)
    scene, t = case.scene, case.exact_t
    # no ray flagged; the depth bound (φ's rounding over |dφ/dt|, reference.depthbound) at least
    # the bracket of adjacent floats
    assert not np.any(np.isnan(t)) and case.judged_mask.all()
    assert np.all(case.exact_t_error_bounds[np.isfinite(t)] >= np.spacing(t[np.isfinite(t)]))
    assert case.exact_t_error_bound <= 5e-9
    hit = np.isfinite(t)
    assert 0.3 * case.n_rays <= hit.sum() <= 0.7 * case.n_rays
    o, d = case.origins[hit], case.directions[hit]
    # φ at the 9 floats t − 4 ulp … t + 4 ulp: the float64 φ changes sign (or is 0) among them
    tt = t[hit, None] + np.arange(-4, 5)[None, :] * np.spacing(t[hit])[:, None]
    s = np.sign(scene.value(o[:, None, :] + tt[..., None] * d[:, None, :]))
    assert np.all(np.any((s[:, 1:] != s[:, :-1]) | (s[:, 1:] == 0), axis=1))
    idx = np.random.default_rng(9).choice(case.n_rays, size=min(64, case.n_rays), replace=False)
    tb = _brentq_first_hits(scene, case.origins[idx], case.directions[idx], case.t_min, case.t_max)
    np.testing.assert_array_equal(np.isfinite(tb), np.isfinite(t[idx]))
    both = np.isfinite(tb)
    assert np.max(np.abs(tb[both] - t[idx][both])) <= 1e-13


def test_understated_bound_is_flagged_by_the_reference_and_the_root_finders():
    """0.5 × the measured slope is below the network's true slope along every ray from inside: the
    numerical reference flags every ray (t = NaN, infinite bound) and sphere tracing reports
    LIPSCHITZ_VIOLATED, never a silent answer; the case's truth comes from the certified bound.
    1.05 × the measured slope is not flagged on these rays (nor the camera's)."""
    from impls import Status
    from tests.conftest import resolve_or_skip

    case = get_case("neural.blob.understated")
    assert "understated" in case.tags
    t, err = first_hit_numeric(case.scene, case.origins, case.directions, case.t_min, case.t_max)
    assert np.all(np.isnan(t) & np.isinf(err))
    assert np.all(np.isfinite(case.exact_t))  # every ray from inside exits: certified by the local bound
    backend = resolve_or_skip("numpy")
    prep = backend.prepare("sphere_trace", case.scene, case.origins, case.directions, dtype="float64",
                           t_min=case.t_min, t_max=case.t_max)
    res = prep.result(prep.run())
    assert np.all(res.status == Status.LIPSCHITZ_VIOLATED), res.status_counts()
    measured = case.scene.child.with_lipschitz("measured")
    cam = get_case("neural.blob.camera.16x16")
    for c in (case, cam):
        tm, em = first_hit_numeric(measured, c.origins, c.directions, c.t_min, c.t_max)
        assert np.all(np.isfinite(em))
        np.testing.assert_allclose(tm, c.exact_t, atol=1e-13)


def test_dt_dtheta_against_differences_of_bracketed_hits(net):
    """dt/dθ (implicit differentiation, closed-form partials) on a sample of weights from every
    layer against (t(θ + h) − t(θ − h))/2h, each hit found by brentq within 1e-3 of the stored one
    (the surface moves by ~1e-6), on rays crossing at |n·d| ≥ 0.3."""
    from scipy.optimize import brentq

    case = get_case("neural.blob.camera.16x16")
    hits = np.flatnonzero(case.hit_mask)
    cos = np.abs(np.einsum("ij,ij->i", net.normal_exact(case.exact_points[hits]), case.directions[hits]))
    idx = np.random.default_rng(10).choice(hits[cos >= 0.3], size=6, replace=False)
    o, d, t0 = case.origins[idx], case.directions[idx], case.exact_t[idx]
    g = net.hit_param_grad(o, d, t0)
    theta = net.param_vector()
    names = net.param_names()
    pick = [i for layer in ("W1", "b1", "W2", "b2", "W3", "b3")
            for i in np.random.default_rng(11).choice([k for k, n in enumerate(names) if f".{layer}" in n], 2)]
    h = 1e-6
    for i in pick:
        ts = []
        for s in (1, -1):
            th = theta.copy()
            th[i] += s * h
            sc = net.with_params(th)
            ts.append([brentq(lambda t: float(sc.value(oo + t * dd)), tt - 1e-3, tt + 1e-3, xtol=1e-15, rtol=4 * EPS)
                       for oo, dd, tt in zip(o, d, t0)])
        fd = (np.array(ts[0]) - np.array(ts[1])) / (2 * h)
        np.testing.assert_allclose(g[:, i], fd, rtol=1e-5, atol=1e-7, err_msg=names[i])


def test_fit_to_the_mesh():
    """The stored network is the blob mesh's SDF to within the fit reported by
    :mod:`reference.make_neural_sdf` (max |φ_net − φ_mesh| < 1e-2, mean < 2e-3 within 0.05 of the
    surface)."""
    pytest.importorskip("igl")
    from reference.make_neural_sdf import fit_error

    w = neural_cases.stored_network().own_params() | neural_cases.stored_network()._stored()
    e = fit_error(w, n=3000)
    assert e["near_max"] < 1e-2 and e["near_mean"] < 2e-3, e
