"""torch ``gradcheck`` and jax ``check_grads`` on the differentiable paths of the backends
(IDR's forward trick and the unrolled sphere tracer, lecture eq. 16), in float64."""

from __future__ import annotations

import numpy as np
import pytest

from impls.methods import METHODS

from impls.core import param_grad
from tests.conformance.common import SPHERE, AlgebraicSphere, camera

SCENES = [SPHERE, AlgebraicSphere()]


def _rays(scene):
    o, d = camera(4)
    t = scene.first_hit(o, d, 0.0)
    hit = np.isfinite(t)
    o, d, t = o[hit], d[hit], t[hit]
    x = o + t[:, None] * d
    g = scene.normal_exact(x)  # direction of ∇φ; gd only needs to be a fixed non-zero constant
    return o, d, t, x, np.einsum("ij,ij->i", g, d)


@pytest.mark.parametrize("scene", SCENES, ids=lambda s: s.kind)
def test_torch_gradcheck(scene):
    torch = pytest.importorskip("torch")
    import array_api_compat.torch as xp

    o, d, t, x, gd = (torch.as_tensor(a, dtype=torch.float64) for a in _rays(scene))
    th = torch.as_tensor(scene.param_vector(), dtype=torch.float64).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda th: param_grad.idr_depth(xp, scene, x, t, gd, th), (th,))
    assert torch.autograd.gradcheck(lambda th: param_grad.unrolled_depth(xp, scene, o, d, 0.0, 12, th), (th,))


@pytest.mark.slow  # compiles many kernels or sweeps a whole catalog
@pytest.mark.parametrize("scene", SCENES, ids=lambda s: s.kind)
def test_jax_check_grads(scene):
    pytest.importorskip("jax")
    import impls.jax.backend  # noqa: F401  (turns on float64)
    import jax.numpy as jnp
    from jax import lax
    from jax.test_util import check_grads

    o, d, t, x, gd = (jnp.asarray(a) for a in _rays(scene))
    th = jnp.asarray(scene.param_vector())
    check_grads(lambda th: param_grad.idr_depth(jnp, scene, x, t, gd, th), (th,), order=2, modes=("fwd", "rev"))
    check_grads(lambda th: param_grad.unrolled_depth(jnp, scene, o, d, 0.0, 12, th, lax.fori_loop), (th,), order=1,
                modes=("fwd", "rev"))


# -- render_surface is differentiable through the hit ----------------------------------------


class _PositionColor:
    """ρ(x) = x: then C = o + t d and ∂C/∂θ = d ⊗ ∂t/∂θ, so the colour's derivative is the hit
    depth's, which the reference has in closed form."""

    def value(self, x, xp):
        return x


class _SineColorField:
    def value(self, x, xp):
        return 0.5 + 0.5 * xp.sin(3.0 * x + 0.25)


DIFF_SCENES = [SPHERE, AlgebraicSphere(center=(0.1, -0.2, 0.05), radius=0.9)]
# the algebraic sphere states its Lipschitz bound on |x| ≤ 4 only, and with θ given the root finder
# has no ray bounds: a search past t = 6 from the camera at distance 3 leaves that domain, where the
# steps see the bound broken (LIPSCHITZ_VIOLATED, colour NaN) instead of clean misses
T_MAX = 6.0


def _surface_rays(scene, n=4):
    o, d = camera(n)
    t = scene.first_hit(o, d, 0.0)
    hit = np.isfinite(t)
    return o, d, hit, scene.hit_param_grad(o[hit], d[hit], t[hit])


# render_surface's knobs as prepare passes them: complete (MethodSpec.validate fills the defaults).
# xtol is the default 1e-12: a depth is CONVERGED only on a bracket of resolved signs that narrow, and
# at 1e-13, a few of φ's modelled roundings here, the camera's most oblique hits are UNCERTIFIED
# (colour NaN: declined; MarchRefine.closing_width)
KNOBS = METHODS["render_surface"].validate(dict(xtol=1e-12, min_step=1e-5, overstep=1e-2, max_steps=4096))


@pytest.mark.parametrize("scene", DIFF_SCENES, ids=lambda s: s.kind)
def test_torch_render_surface_gradient_is_the_hit_depth_gradient(scene):
    torch = pytest.importorskip("torch")
    from impls import registry
    from impls.core.rendering import render_surface

    b = registry.resolve("torch:cpu")
    o, d, hit, dt_exact = _surface_rays(scene)
    O, D = (torch.as_tensor(a, dtype=torch.float64) for a in (o, d))
    th = torch.as_tensor(scene.param_vector(), dtype=torch.float64)

    def color(theta, field=_PositionColor()):
        return render_surface(b, scene, O, D, t_min=0.0, t_max=T_MAX, t_hit=None, color=field, theta=theta,
                              **KNOBS)["color"]

    J = torch.autograd.functional.jacobian(color, th).numpy()  # (n, 3, P)
    want = np.zeros_like(J)  # misses: colour 0, derivative 0
    want[hit] = d[hit][:, :, None] * dt_exact[:, None, :]
    assert np.abs(J - want).max() < 1e-9
    # a non-linear colour field, against central differences that re-solve the hit
    thr = th.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: color(t, _SineColorField()), (thr,), eps=1e-6, atol=1e-6)


@pytest.mark.slow  # compiles many kernels or sweeps a whole catalog
@pytest.mark.parametrize("scene", DIFF_SCENES, ids=lambda s: s.kind)
def test_jax_render_surface_gradient_is_the_hit_depth_gradient(scene):
    pytest.importorskip("jax")
    import jax
    import jax.numpy as jnp
    from jax.test_util import check_grads

    from impls import registry
    from impls.core.rendering import render_surface

    b = registry.resolve("jax:cpu")
    o, d, hit, dt_exact = _surface_rays(scene)
    O, D = jnp.asarray(o), jnp.asarray(d)
    th = jnp.asarray(scene.param_vector())

    def color(theta, field=_PositionColor()):
        return render_surface(b, scene, O, D, t_min=0.0, t_max=T_MAX, t_hit=None, color=field, theta=theta,
                              **KNOBS)["color"]

    for jac in (jax.jacfwd, jax.jacrev):
        J = np.asarray(jax.jit(jac(color))(th))
        want = np.zeros_like(J)
        want[hit] = d[hit][:, :, None] * dt_exact[:, None, :]
        assert np.abs(J - want).max() < 1e-9
    check_grads(lambda t: color(t, _SineColorField()), (th,), order=1, modes=("fwd", "rev"), eps=1e-6)


def test_numpy_render_surface_is_the_colour_at_the_hit():
    from impls import registry
    from impls.core.rendering import render_surface

    o, d, hit, _ = _surface_rays(SPHERE)
    out = render_surface(registry.resolve("numpy"), SPHERE, o, d, t_min=0.0, t_max=10.0, t_hit=None,
                         color=_PositionColor(), **KNOBS)
    t = SPHERE.first_hit(o, d, 0.0)
    assert np.abs(out["color"][hit] - (o + t[:, None] * d)[hit]).max() < 1e-12
    assert np.all(out["color"][~hit] == 0)


@pytest.mark.parametrize("backend_id", ["numpy", "torch:cpu", "jax:cpu"])
def test_ray_eval_derivative_is_the_exact_directional_derivative(backend_id):
    """``ray_eval``'s dφ/dt (the Newton refiners' derivative; torch's by one backward pass over the
    sum of the rays' φ) is ⟨∇φ, d⟩ from the scenes' closed-form jets, at points along camera
    rays of a CSG union (max/min branches), a torus and a sphere; φ is the scene's own value."""
    from reference.csg import Union
    from reference.primitives import Box, Torus
    from tests.conftest import resolve_or_skip

    b = resolve_or_skip(backend_id)
    o, d = camera(8)
    ts = np.linspace(1.5, 4.0, len(o))
    for scene in (Union(Torus(1.0, 0.25), Box((0.4, 0.4, 0.4))), Torus(1.0, 0.25), SPHERE):
        x = o + ts[:, None] * d
        phi, grad, _ = scene.jet(x)
        ev = b.ray_eval(scene)
        f, df, _ = ev(b.asarray(o, "float64"), b.asarray(d, "float64"), b.asarray(ts, "float64"), True)
        f, df = b.to_numpy(f), b.to_numpy(df)
        np.testing.assert_allclose(f, scene.value(x), rtol=0, atol=1e-14)
        # numpy's is a central difference (impls.numpy.derivatives: error O(h²|φ‴|), h ≈ 6e-6·|t|);
        # the autodiff backends' is exact to rounding
        rtol = 1e-7 if backend_id == "numpy" else 1e-12
        np.testing.assert_allclose(df, np.einsum("ij,ij->i", grad, d), rtol=rtol, atol=1e-14)


def test_torch_prepared_runs_record_no_autograd_graph():
    """``prepare``'s outputs go to numpy, so a timed torch call records no graph, even with grad
    mode on (torch's default).  Before, ``dt_finite_diff``'s Newton re-solves kept the graphs of
    their dφ/dt through the iterates (1.5 GB at 512² rays on the torus) and its output required
    grad; every method's outputs must now be plain tensors, and the same as with grad mode off."""
    torch = pytest.importorskip("torch")
    from impls.registry import resolve
    from reference.cases import get_case

    case = get_case("torus.camera.32x32")
    o, d = case.origins[::16], case.directions[::16]
    t_hit = case.scene.first_hit(o, d, t_min=case.t_min)
    b = resolve("torch")
    for method in b.methods():
        given = {"t_hit": t_hit} if METHODS[method].needs_t_hit else {}
        p = b.prepare(method, case.scene, o, d, t_min=case.t_min, t_max=case.t_max, **given)
        with torch.enable_grad():
            out = p.run()
        assert not [k for k, v in out.items() if v.requires_grad], method
        with torch.no_grad():
            off = p.result(p.run())
        on = p.result(out)
        np.testing.assert_array_equal(on.t, off.t, err_msg=method)
        for k, v in on.outputs.items():
            np.testing.assert_array_equal(v, off.outputs[k], err_msg=f"{method} {k}")


@pytest.mark.parametrize("backend_id", [
    "numpy", "torch:cpu", pytest.param("jax:cpu", marks=pytest.mark.slow)])
def test_finite_differences_decline_a_ray_whose_perturbed_twin_misses(backend_id):
    """``dt_finite_diff`` re-solves t(θ ± h) by Newton from t̂.  On a ray grazing the torus's
    outer equator 0.4 h inside it, the ray of R − h misses: its Newton steps run off, and the
    quotient (87 % off on a 256² camera's such ray) was returned CONVERGED.  It is now declined
    (ILL_CONDITIONED); a ray whose twins both hit keeps CONVERGED and the exact dt/dR."""
    from impls.registry import resolve
    from reference.primitives import Torus

    scene = Torus(1.0, 0.25)
    R, r, h = 1.0, 0.25, 1e-6
    x0 = np.array([R + r - 0.4 * h, 0.6])  # grazing; and a ray through the tube's flank
    o = np.stack([x0, np.full(2, -2.0), np.zeros(2)], axis=1)
    d = np.tile([0.0, 1.0, 0.0], (2, 1))
    y = -np.sqrt((R + r) ** 2 - x0 ** 2)  # both hit the outer flank, ρ = R + r
    t_hit = y + 2.0
    be = resolve(backend_id)
    p = be.prepare("dt_finite_diff", scene, o, d, dtype="float64", t_min=0.0, t_max=6.0, t_hit=t_hit)
    res = p.result(p.run())
    assert list(res.status) == [-6, 0]  # ILL_CONDITIONED, CONVERGED
    # the flank ray: ρ = R + r along it, so dt/dR = −(∂φ/∂R)/⟨∇φ, d⟩ = 1/⟨n, d⟩ with n = (x, y)/ρ
    cos = abs(y[1]) / (R + r)
    assert res.outputs["dt_dtheta"][1, 0] == pytest.approx(-1.0 / cos, rel=1e-6)


def test_numpy_float32_hit_depth_gradient_steps_by_float32s_epsilon():
    """numpy's dt/dθ is a central difference in θ (impls.core.param_grad.central_jacobian).  Its step
    was float64's ε^{1/3}·max(1, |θ|) in float32 runs too, a few float32 spacings of θ, divided by
    the unrounded 2h: on a rotated torus's 64² camera every hit's dt/dθ came out up to 13 % off
    (float64, like the run, in dtype).  With float32's ε and the rounded divisor: 1.1e-3 at most,
    against torch's autodiff 1.5e-5; the finite differences' own limit in float32 (φ's rounding
    over the step), not a wrong step."""
    from impls import registry
    from reference import Case, Torus, Transform, rays

    scene = Transform.from_rotvec(Torus(0.8, 0.25), (1.1, 0.2, 0.0), (0.0, 0.1, 0.0))
    o, d = rays.pinhole(eye=(0.6, 1.3, 3.2), look_at=(0, 0, 0), fov_deg=30, width=64, height=64)
    case = Case(id="test.torus.rotated", scene=scene, origins=o, directions=d, t_min=0.0, t_max=7.0)
    exact = case.exact_dt_dtheta
    for method in ("dt_implicit", "dt_idr"):
        p = registry.resolve("numpy").prepare(method, scene, o, d, dtype="float32", t_min=0.0, t_max=7.0,
                                              t_hit=case.exact_t)
        r = p.result(p.run())
        got = np.asarray(r.outputs["dt_dtheta"])
        assert got.dtype == np.float32
        ok = (np.asarray(r.status) == 0) & case.hit_mask
        assert ok.sum() > 1000
        rel = np.max(np.abs(got.astype(np.float64) - exact) / np.maximum(1.0, np.abs(exact)), axis=1)[ok]
        assert rel.max() <= 5e-3, (method, rel.max())


def test_float32_finite_difference_step_is_at_least_the_square_root_of_epsilon():
    """``dt_finite_diff`` re-solves the hit at θ_i ± h_i; its default h = 1e-6 is below what float32
    resolves, and the quotient was the re-solved depths' rounding: dt/dθ 0.8–2.2 off on every
    CONVERGED ray of a user blob's 64² camera, numpy and torch alike.  The step is now at least √ε
    of the dtype (float64 keeps h): the median error is 1.9e-4, the worst 0.14 (rays whose
    slope amplifies the rounding), float32's finite-difference limit."""
    from impls import registry
    from reference import CallableField, Case, rays

    def blob(x, xp, theta):
        return xp.sqrt(xp.sum(x * x, axis=-1)) - theta[0] + theta[1] * xp.sin(3.0 * x[..., 0]) * xp.cos(2.0 * x[..., 1])

    scene = CallableField(blob, lipschitz=1.8, name="test.fd.blob", smooth=True, params=(0.9, 0.1))
    o, d = rays.pinhole(eye=(0.6, 1.3, 3.2), look_at=(0, 0, 0), fov_deg=30, width=64, height=64)
    case = Case(id="test.fd.blob.cam", scene=scene, origins=o, directions=d, t_min=0.0, t_max=7.0)
    exact = case.exact_dt_dtheta
    p = registry.resolve("numpy").prepare("dt_finite_diff", scene, o, d, dtype="float32", t_min=0.0, t_max=7.0,
                                          t_hit=case.exact_t)
    r = p.result(p.run())
    ok = (np.asarray(r.status) == 0) & case.hit_mask
    assert ok.sum() > 3000
    rel = np.max(np.abs(np.asarray(r.outputs["dt_dtheta"], np.float64) - exact) / np.maximum(1.0, np.abs(exact)),
                 axis=1)[ok]
    assert np.median(rel) <= 1e-3 and rel.max() <= 0.3, (np.median(rel), rel.max())


def test_float32_unrolled_tracer_converges_to_rounding_and_its_derivative_is_the_chain_rule():
    """``dt_unrolled`` stopped only at |φ|/L ≤ 1e-9, below float32's rounding of φ (~1e-6 at these
    depths): in float32 nearly every hit ended MAX_ITER.  It now stops at φ's rounding as well
    (``impls.core.rootfind.resolution``).  numpy, without autodiff, took dt/dθ as central
    differences of the whole 64-step trace; with the looser stop those differenced two perturbed
    trajectories of grazing rays, up to 1.6e5 off on CONVERGED rays of the catalog's scaled torus,
    so numpy now writes out the chain rule through every step (``unrolled_chain_rule``): the
    forward-mode derivative torch's autodiff takes, which it must match ray by ray.  Against the
    exact dt/dθ both err by up to ~3e-2 on the few near-grazing hits, where the tracer's slow
    approach leaves the derivative of the 64-step map short of the hit's: the method's own
    float32 limit, the same on both backends."""
    from impls import registry
    from reference import Case, Torus, Transform, rays
    from reference.implicits import Scaled

    scene = Scaled(Transform.from_rotvec(Torus(0.8, 0.25), (1.1, 0.2, 0.0), (0.0, 0.1, 0.0)), 3.0)
    o, d = rays.pinhole(eye=(0.6, 1.3, 3.2), look_at=(0, 0, 0), fov_deg=30, width=48, height=48)
    case = Case(id="test.unrolled.f32", scene=scene, origins=o, directions=d, t_min=0.0, t_max=7.0)
    exact = case.exact_dt_dtheta
    got = {}
    for backend_id in ("numpy", "torch:cpu"):
        p = registry.resolve(backend_id).prepare("dt_unrolled", scene, o, d, dtype="float32", t_min=0.0, t_max=7.0)
        r = p.result(p.run())
        status = np.asarray(r.status)
        ok = (status == 0) & case.hit_mask
        assert ok.sum() >= 0.9 * case.hit_mask.sum(), {s: int((status == s).sum()) for s in set(status.tolist())}
        got[backend_id] = (np.asarray(r.outputs["dt_dtheta"], np.float64), ok)
        rel = np.max(np.abs(got[backend_id][0] - exact) / np.maximum(1.0, np.abs(exact)), axis=1)[ok]
        assert np.median(rel) <= 1e-3 and rel.max() <= 5e-2, (backend_id, np.median(rel), rel.max())
    (a, ok_a), (b, ok_b) = got["numpy"], got["torch:cpu"]
    both = ok_a & ok_b
    assert both.sum() >= 0.9 * case.hit_mask.sum()
    diff = np.max(np.abs(a - b) / np.maximum(1.0, np.abs(b)), axis=1)[both]
    assert diff.max() <= 2e-3, diff.max()
