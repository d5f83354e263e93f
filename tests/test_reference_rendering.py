"""The continuous rendering reference against closed forms, and the shared discrete formulas."""

from __future__ import annotations

import mpmath
import numpy as np
import pytest
from scipy.special import log_expit

from reference import rendering as R
from reference.primitives import Plane, Sphere

S, T_MIN, T_MAX = 20.0, 0.0, 3.0
RAYS_O = np.array([[0.0, 0.0, 1.0], [0.3, -0.2, 1.0]])
RAYS_D = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]])
RGB = np.array([0.2, 0.5, 0.9])


class ConstColor:
    def value(self, x, xp=np):
        return np.ones(x.shape[:-1] + (3,)) * RGB


def _tau_plane(model, t):
    """Optical depth ∫_{T_MIN}^t σ for the plane φ = 1 − t along these rays (closed forms)."""
    sp = lambda z: np.logaddexp(0.0, z)
    if model == "nerf":  # σ = s·sigm(s(t − 1))
        return sp(S * (t - 1)) - sp(S * (T_MIN - 1))
    if model == "neus":  # T = Φ_s(φ(t))/Φ_s(φ(t_min))
        return -(log_expit(S * (1 - t)) - log_expit(S * (1 - T_MIN)))
    # volsdf: σ = s·½e^{−s(1−t)} before the plane, s(1 − ½e^{−s(t−1)}) after it
    before = 0.5 * (np.exp(-S * (1 - min(t, 1.0))) - np.exp(-S * (1 - T_MIN)))
    after = 0.0 if t <= 1 else S * (t - 1) + 0.5 * (np.exp(-S * (t - 1)) - 1)
    return before + after


@pytest.mark.parametrize("model", ["nerf", "neus", "volsdf"])
def test_plane_with_logistic_density_matches_the_closed_form(model):
    C, err, T = R.render_exact(Plane(), ConstColor(), model, S, RAYS_O, RAYS_D, T_MIN, T_MAX, return_transmittance=True)
    tau = _tau_plane(model, T_MAX)
    np.testing.assert_allclose(T, np.exp(-tau), rtol=0, atol=1e-12)
    np.testing.assert_allclose(C, np.outer(1 - np.exp(-tau), RGB) * np.ones((2, 1)), rtol=0, atol=1e-10)
    assert np.all(err <= 1e-10)
    assert np.all(np.abs(C - (1 - np.exp(-tau)) * RGB) <= err[:, None] + 1e-15)


def test_varying_colour_against_mpmath_quadrature_of_the_closed_form_depth():
    """ρ varies along the ray: C by 30-digit tanh-sinh (mpmath.quad) of e^{−τ(t)} σ(t) ρ(t) with
    the closed-form τ of the NeRF-style density on the plane."""
    col = R.SineColor(frequency=3.0)
    C, err = R.render_exact(Plane(), col, "nerf", S, RAYS_O[:1], RAYS_D[:1], T_MIN, T_MAX)
    mpmath.mp.dps = 30
    s = mpmath.mpf(S)
    sp = lambda z: mpmath.log(1 + mpmath.exp(z))
    for c in range(3):
        a = col.directions[c]
        f = lambda t: (mpmath.exp(-(sp(s * (t - 1)) - sp(s * (T_MIN - 1)))) * s / (1 + mpmath.exp(-s * (t - 1)))
                       * (mpmath.mpf(1) / 2 + mpmath.sin(col.frequency * a[2] * (1 - t) + col.phases[c]) / 2))
        ref = mpmath.quad(f, [T_MIN, 1 - 16 / S, 1 - 4 / S, 1, 1 + 4 / S, 1 + 16 / S, T_MAX])
        assert abs(C[0, c] - float(ref)) <= max(err[0], 1e-14)


def test_discrete_compositing_converges_to_the_integral():
    """The shared discrete formulas (α = 1 − e^{−σδ}, composite) tend to render_exact as the
    step shrinks.  Compositing with left-point samples integrates piecewise-constant σ and ρ
    exactly, i.e. a left Riemann sum of Tσρ, whose O(δ) Euler–Maclaurin term −δ/2·[Tσρ]_{t_min}^{t_max}
    vanishes here (σ ≈ 0 at the start, T ≈ 0 at the end): the error is O(δ²), ratio 16 per 4×."""
    sph = Sphere(radius=0.8)
    o, d = np.array([[0.1, 0.2, 3.0]]), np.array([[0.0, 0.0, -1.0]])
    col = R.SineColor()
    C, err = R.render_exact(sph, col, "volsdf", 10.0, o, d, 0.0, 6.0)
    errs = []
    for N in (500, 2000, 8000):
        t = np.linspace(0.0, 6.0, N + 1)
        mid = t[:-1]
        x = o + mid[:, None] * d
        a = R.alpha_from_density(R.density("volsdf", sph.value(x), 10.0), np.diff(t))
        c_disc, _ = R.composite(a, col.value(x))
        errs.append(np.max(np.abs(c_disc - C[0])))
    assert errs[0] > errs[1] > errs[2] and errs[2] < 2e-3
    assert errs[1] / errs[2] == pytest.approx(16.0, rel=0.3)


def test_colour_lipschitz_bound_holds_and_is_nearly_attained():
    col = R.SineColor(frequency=5.0)
    rng = np.random.default_rng(0)
    x = rng.uniform(-2, 2, size=(20000, 3))
    y = x + 1e-4 * rng.normal(size=x.shape)
    ratio = np.linalg.norm(col.value(x) - col.value(y), axis=1) / np.linalg.norm(x - y, axis=1)
    assert ratio.max() <= col.lipschitz
    assert ratio.max() >= 0.6 * col.lipschitz


@pytest.mark.parametrize("lib", ["torch", "jax"])
def test_density_formulas_agree_across_libraries(lib):
    phi = np.linspace(-2, 2, 101)
    dphi = np.cos(np.linspace(0, 6, 101))
    if lib == "torch":
        torch = pytest.importorskip("torch")
        from array_api_compat import torch as xp

        conv, back = torch.from_numpy, lambda a: a.numpy()
    else:
        jax = pytest.importorskip("jax")
        jax.config.update("jax_enable_x64", True)
        import jax.numpy as xp

        conv, back = xp.asarray, np.asarray
    for model in ("nerf", "volsdf", "neus"):
        ref = R.density(model, phi, 7.0, np, dphi_dt=dphi)
        out = back(R.density(model, conv(phi), 7.0, xp, dphi_dt=conv(dphi)))
        np.testing.assert_allclose(out, ref, rtol=4e-16, atol=1e-300)
    a = R.neus_alpha(phi[:-1], phi[1:], 7.0)
    np.testing.assert_allclose(back(R.neus_alpha(conv(phi[:-1]), conv(phi[1:]), 7.0, xp)), a, rtol=4e-16)
    rgb = np.random.default_rng(0).uniform(size=(100, 3))
    c_ref, t_ref = R.composite(a, rgb)
    c, t = R.composite(conv(a), conv(rgb), xp)
    np.testing.assert_allclose(back(c), c_ref, rtol=1e-14)
    np.testing.assert_allclose(back(t), t_ref, rtol=1e-14)


@pytest.mark.parametrize("lib", ["numpy", "torch", "jax"])
def test_neus_alpha_stays_finite_at_high_sharpness_with_finite_gradients(lib):
    """A section rising from deep inside (s·φ from −5,000 to −1,000 at s = 1e4): α = 0, not the
    NaN that 0·(−inf) made of an overflowed expm1 (every ray leaving the solid was NON_FINITE at
    sharpness ≥ 1e4, in float64 too); entering sections keep α ∈ (0, 1]; and under autodiff the
    gradient is finite everywhere (no untaken inf branch of a where)."""
    phi = np.array([0.3, 0.01, -0.01, -0.5, -0.1, 0.2, 0.5])
    for s in (7.0, 1e4, 1e8):
        a = R.neus_alpha(phi[:-1], phi[1:], s)
        assert np.all(np.isfinite(a)) and np.all((a >= 0) & (a <= 1)), (s, a)
        assert a[3] == 0 and a[4] == 0 and a[2] > 0.9  # rising inside: none; entering deeper: nearly all
    if lib == "numpy":
        return
    if lib == "torch":
        torch = pytest.importorskip("torch")
        from array_api_compat import torch as xp

        p = torch.tensor(phi, requires_grad=True)
        R.neus_alpha(p[:-1], p[1:], 1e4, xp).sum().backward()
        grad = p.grad.numpy()
        out = R.neus_alpha(torch.from_numpy(phi[:-1]), torch.from_numpy(phi[1:]), 1e4, xp).numpy()
    else:
        jax = pytest.importorskip("jax")
        jax.config.update("jax_enable_x64", True)
        import jax.numpy as xp

        grad = np.asarray(jax.grad(lambda p: R.neus_alpha(p[:-1], p[1:], 1e4, xp).sum())(xp.asarray(phi)))
        out = np.asarray(R.neus_alpha(xp.asarray(phi[:-1]), xp.asarray(phi[1:]), 1e4, xp))
    np.testing.assert_allclose(out, R.neus_alpha(phi[:-1], phi[1:], 1e4), rtol=4e-16)
    assert np.all(np.isfinite(grad)), grad


def test_volume_neus_at_high_sharpness_answers_every_ray():
    """volume_neus_uniform on a sphere camera at sharpness 1e4 (numpy, float64 and float32): no
    NON_FINITE ray, colours in [0, 1]."""
    from impls import registry
    from impls.protocol import Status
    from reference import rays

    o, d = rays.pinhole(eye=(0, 0, 3), look_at=(0, 0, 0), fov_deg=40, width=16, height=16)
    b = registry.resolve("numpy")
    for dt in ("float64", "float32"):
        p = b.prepare("volume_neus_uniform", Sphere(), o, d, dtype=dt, t_min=0.0, t_max=6.0, sharpness=1e4)
        r = p.result(p.run())
        assert not np.any(r.status == Status.NON_FINITE), (dt, int(np.sum(r.status == Status.NON_FINITE)))
        col = r.outputs["color"]
        assert np.all(np.isfinite(col)) and np.all((col >= 0) & (col <= 1)), dt


def test_bad_inputs_are_named():
    with pytest.raises(ValueError, match="unisurf"):
        R.render_exact(Plane(), ConstColor(), "unisurf", 10.0, RAYS_O, RAYS_D, 0.0, 1.0)
    with pytest.raises(ValueError, match="model"):
        R.density("nerfs", np.zeros(3), 1.0)
    with pytest.raises(ValueError, match="sharpness"):
        R.density("nerf", np.zeros(3), -1.0)
    with pytest.raises(ValueError, match="t_max"):
        R.render_exact(Plane(), ConstColor(), "nerf", 10.0, RAYS_O, RAYS_D, 0.0, np.inf)
    with pytest.raises(ValueError, match="dphi_dt"):
        R.density("neus", np.zeros(3), 1.0)



def test_neus_on_a_field_without_a_jet_is_a_named_error_that_bench_records_as_a_skip():
    """NeuS's density reads ∂φ/∂t, which a user's ``CallableField`` not declared smooth does not give:
    ``render_exact`` says so (a ValueError naming the jet and the fix) instead of a NotImplementedError from
    inside the quadrature, and bench records the integral as a quantity it could not check (the
    configuration's ``color_vs_surface`` is still measured), not as a failed configuration."""
    from bench.run.references import NotApplicable, ReferenceOptions, exact_color
    from impls.methods import get_method
    from reference import CallableField, rays
    from reference.cases import Case

    field = CallableField(lambda x, xp: xp.sqrt(xp.sum(x * x, axis=-1)) - 0.5, lipschitz=1.0, name="tests.ball")
    with pytest.raises(ValueError, match=r"jet.*smooth=True"):
        R.render_exact(field, ConstColor(), "neus", 10.0, RAYS_O, RAYS_D, 0.0, 1.0)
    R.render_exact(field, ConstColor(), "nerf", 10.0, RAYS_O[:2], RAYS_D[:2], 0.0, 1.0)  # φ alone: computed
    o, d = rays.pinhole(eye=(0.0, 0.0, 2.0), look_at=(0.0, 0.0, 0.0), fov_deg=30.0, width=2, height=2)
    case = Case(id="tests.ball.neus", scene=field, origins=o, directions=d, t_min=0.0, t_max=4.0)
    spec = get_method("volume_neus_uniform")
    with pytest.raises(NotApplicable, match="jet"):
        exact_color(case, spec, spec.validate({}), {"_options": ReferenceOptions(expensive=True, disk=None)})


def test_case_exact_colors_are_cached_and_match_render_exact():
    from reference.cases import Case

    case = Case(id="tmp.plane", scene=Plane(), origins=RAYS_O, directions=RAYS_D, t_min=T_MIN, t_max=T_MAX)
    C, err, T = case.exact_colors("volsdf", S)
    assert case.exact_colors("volsdf", S)[0] is C
    C2, err2 = R.render_exact(Plane(), case.color_field, "volsdf", S, RAYS_O, RAYS_D, T_MIN, T_MAX)
    np.testing.assert_array_equal(C, C2)
    np.testing.assert_allclose(T, np.exp(-_tau_plane("volsdf", T_MAX)), atol=1e-12)
