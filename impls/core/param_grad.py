"""Hit-depth derivatives dt/dθ (θ = ``scene.param_vector()``, pre-order), written once.

A backend supplies ``backend.grad_hess`` (∇ₓφ, see :mod:`impls.core.pointwise`),
``backend.theta_jacobian(fun, theta) -> (J, cost)`` — the Jacobian (n, P) of a map θ ↦ (n,) array (forward-mode
autodiff in torch/jax, central differences in numpy) — ``backend.ray_eval`` (φ and dφ/dt along rays,
used by the finite-difference method's Newton steps) and ``backend.fori_loop`` (the unrolled
tracer's loop).

* ``dt_implicit`` — lecture eq. 7–8: from φ(o + t(θ) d; θ) = 0,
  dt/dθ = −(∂φ/∂θ) / ⟨∇ₓφ, d⟩ at x̂ = o + t̂ d.
* ``dt_idr`` — the forward trick (IDR, Yariv et al. 2020; DVR, Niemeyer et al. 2020):
  t(θ) = t̂ − φ(x̂; θ) / sg(⟨∇ₓφ(x̂; θ₀), d⟩), sg = stop-gradient; its Jacobian at θ₀ equals
  eq. 8, and its value is t̂ plus one Newton correction (returned as ``t``).
* ``dt_unrolled`` — lecture eq. 16: t_{k+1} = t_k + φ(o + t_k d; θ)/L from t_min, ``steps``
  steps, differentiated through every step (signed φ: rays start outside).  Status CONVERGED
  when |φ(x_steps)|/L ≤ max(``UNROLLED_TOL``, φ's rounding there) (the unrolled tracer reached
  the surface to what the dtype resolves: its step φ/L is then below the rounding of φ, modelled
  as the certified root finders model it, :func:`impls.core.rootfind.resolution`), MISS when t
  left [t_min, t_max], else MAX_ITER (its derivative is then not dt/dθ of a hit).  (With 1e-9
  alone, float32, whose φ rounds by ~1e-6 at these depths, ended MAX_ITER on every ray that did
  not land on φ = 0 by chance: 12,887 of a camera's 12,950 hits.)
* ``dt_finite_diff`` — (t(θ⁺) − t(θ⁻)) / (θ⁺_i − θ⁻_i), θ^± = θ ± h_i e_i rounded to the dtype
  (≈ 2h_i), h_i = h·max(1, |θ_i|), each t re-solved from t̂ by ``NEWTON_STEPS`` safeguard-free
  Newton steps (the root moves by O(h)); ILL_CONDITIONED where the last Newton step of either
  re-solve is above √ε·max(1, |t|): it did not converge (the perturbed ray misses, as a grazing
  hit's neighbour can), so the quotient is not a derivative.

Guard: where |⟨∇φ, d⟩|/|∇φ| < ``min_cos`` (grazing) the status is ILL_CONDITIONED (the value is
still returned: it is the method's answer, just not trustworthy).
"""

from __future__ import annotations

import numpy as np

from .pointwise import finish, hit_points
from .methods_root import rounding_gain, rounding_scale
from .rootfind import CONV, MAXI, MISS, _magnitude, _quiet, resolution

ILL = -6  # Status.ILL_CONDITIONED
NEWTON_STEPS = 8
UNROLLED_TOL = 1e-9


def _dtype_name(xp, like) -> str:
    return "float64" if xp.finfo(like.dtype).bits == 64 else "float32"


def theta0(backend, scene, like):
    return backend.asarray(scene.param_vector(), _dtype_name(backend.xp, like))


def _guard(xp, status, g, d, min_cos):
    gd = xp.sum(g * d, axis=-1)
    cos = gd / xp.sqrt(xp.sum(g * g, axis=-1))
    # grazing where cos is a number below min_cos; a NaN cos (∇φ not finite, or zero) is left to
    # ``finish``, which makes it NON_FINITE (ILL_CONDITIONED keeps its value, so a NaN there would
    # be a NaN under a status that promises a value)
    return gd, xp.astype(xp.where((status == CONV) & (xp.abs(cos) < min_cos), ILL, status), xp.int32)


def _finish_dt(xp, status, dt, t, cost):
    # ILL_CONDITIONED keeps its value; ``finish`` blanks only what is not CONVERGED, so swap in
    ill = status == ILL
    out = finish(xp, xp.astype(xp.where(ill, CONV, status), xp.int32), {"dt_dtheta": dt}, t, cost)
    # grazing takes precedence over NON_FINITE (⟨∇φ, d⟩ = 0 exactly gives ±inf, blanked to NaN)
    out["status"] = xp.astype(xp.where(ill, ILL, out["status"]), xp.int32)
    return out


def idr_depth(xp, scene, x, t_hit, gd, theta):
    """IDR's differentiable depth t̂ − φ(x̂; θ)/gd, gd = ⟨∇φ(x̂; θ₀), d⟩ held constant."""
    return t_hit - scene.value(x, xp, theta) / gd


def unrolled_depth(xp, scene, o, d, t_min, steps, theta, fori_loop=None):
    """t after ``steps`` differentiable sphere-tracing steps t ← t + φ(o + t d; θ)/L (eq. 16)."""
    inv_lip = 1.0 / float(scene.info.lipschitz)
    t = xp.full_like(o[:, 0], t_min)
    return (fori_loop or python_fori)(0, steps, lambda _, t: t + scene.value(o + t[:, None] * d, xp, theta) * inv_lip, t)


def python_switch(index, branches, *operands):
    """``lax.switch`` semantics as a plain call (numpy, torch): the branch of ``index``, clamped
    to the branches' range."""
    return branches[min(max(int(index), 0), len(branches) - 1)](*operands)


def python_fori(lower, upper, body, init):
    """``lax.fori_loop`` semantics as a plain loop (numpy, torch)."""
    val = init
    for i in range(lower, upper):
        val = body(i, val)
    return val


def dt_implicit(backend, scene, o, d, *, t_min, t_max, t_hit, min_cos):
    xp = backend.xp
    x, status = hit_points(xp, o, d, t_hit)
    g, _, c1 = backend.grad_hess(scene, x, False)
    gd, status = _guard(xp, status, g, d, min_cos)
    J, c2 = backend.theta_jacobian(lambda th: scene.value(x, xp, th), theta0(backend, scene, o))
    with _quiet(xp):
        dt = -J / gd[:, None]
    return _finish_dt(xp, status, dt, t_hit, c1 + c2)


def dt_idr(backend, scene, o, d, *, t_min, t_max, t_hit, min_cos):
    xp = backend.xp
    x, status = hit_points(xp, o, d, t_hit)
    g, _, c1 = backend.grad_hess(scene, x, False)
    gd, status = _guard(xp, status, g, d, min_cos)  # gd is a constant here: the stop-gradient
    th0 = theta0(backend, scene, o)
    t_of = lambda th: idr_depth(xp, scene, x, t_hit, gd, th)  # noqa: E731
    J, c2 = backend.theta_jacobian(t_of, th0)
    return _finish_dt(xp, status, J, t_of(th0), c1 + c2 + 1)


def unrolled_chain_rule(backend, scene, o, d, t_min, steps, th0):
    """(t, dt/dθ, cost) after ``steps`` tracer steps (eq. 16), differentiated through every step
    by the chain rule written out: t_{k+1} = t_k + φ(x_k; θ)/L and
    D_{k+1} = D_k + (∂φ/∂θ(x_k) + ⟨∇ₓφ(x_k), d⟩·D_k)/L, D₀ = 0, x_k = o + t_k d — the forward-mode
    derivative that autodiff computes, for a backend without autodiff, with its own per-point
    ∇ₓφ and ∂φ/∂θ (numpy: central differences of φ at a point).  Central differences of the
    whole trace instead difference two trajectories 2h apart: in float32 a grazing ray's perturbed
    trace can miss or stall elsewhere, and dt/dθ came out up to 1.6e5 off on CONVERGED rays."""
    xp = backend.xp
    inv_lip = 1.0 / float(scene.info.lipschitz)
    t = xp.full_like(o[:, 0], t_min)
    D, cost = backend.asarray(np.zeros((o.shape[0], int(th0.shape[0]))), _dtype_name(xp, o)), 0
    for _ in range(steps):
        x = o + t[:, None] * d
        g, _, c1 = backend.grad_hess(scene, x, False)
        J, c2 = backend.theta_jacobian(lambda th, x=x: scene.value(x, xp, th), th0)
        with _quiet(xp):  # a ray that left the scene: inf·0, its status says so
            D = D + (J + xp.sum(g * d, axis=-1)[:, None] * D) * inv_lip
        t = t + scene.value(x, xp, th0) * inv_lip
        cost = cost + c1 + c2 + 1
    return t, D, cost


def dt_unrolled(backend, scene, o, d, *, t_min, t_max, t_hit, steps, min_cos):
    """dt/dθ of the unrolled tracer (module docstring): by the backend's forward-mode autodiff
    through the traced loop, or, without autodiff, by :func:`unrolled_chain_rule`."""
    xp = backend.xp
    inv_lip = 1.0 / float(scene.info.lipschitz)

    def t_of(th):
        return unrolled_depth(xp, scene, o, d, t_min, steps, th, backend.fori_loop)

    th0 = theta0(backend, scene, o)
    chain = getattr(backend.capabilities, "autodiff", None) is None
    if chain:
        t, J, c_chain = unrolled_chain_rule(backend, scene, o, d, t_min, steps, th0)
    else:
        t = t_of(th0)
    far = t > t_max  # left the range (a NaN depth is not a miss: hit_points makes it NON_FINITE)
    x, status = hit_points(xp, o, d, xp.where(far, xp.full_like(t, float("inf")), t))
    status = xp.astype(xp.where((status == CONV) & far, MISS, status), xp.int32)
    mag = _magnitude(xp, o, rounding_scale(scene))
    tol = xp.maximum(resolution(xp, t, mag, rounding_gain(scene)), xp.full_like(t, UNROLLED_TOL))
    reached = xp.abs(scene.value(x, xp)) * inv_lip <= tol
    status = xp.astype(xp.where((status == CONV) & ~reached, MAXI, status), xp.int32)
    g, _, c1 = backend.grad_hess(scene, x, False)
    _, status = _guard(xp, status, g, d, min_cos)
    if chain:
        cost = c1 + c_chain + 1
    else:
        J, c2 = backend.theta_jacobian(t_of, th0)
        cost = c1 + c2 * steps + steps + 1
    out = _finish_dt(xp, status, J, xp.where(far, xp.full_like(t, float("inf")), t), cost)
    out["iterations"] = xp.full_like(out["iterations"], steps)
    return out


def dt_finite_diff(backend, scene, o, d, *, t_min, t_max, t_hit, h, min_cos):
    """One column of dt/dθ per parameter, in ``backend.fori_loop`` over the parameters: under
    jax's ``lax.fori_loop`` the 2·NEWTON_STEPS re-solves are traced once, not once per
    parameter (a Python loop unrolled them into one graph: the 350-weight MLP's took XLA 4 min
    to compile); numpy and torch run it as a plain loop.  Parameter i is perturbed by
    ±h_i·e_i, h_i = max(h, √ε)·max(1, |θ_i|) (ε the dtype's: float64 keeps the default h, float32
    steps 3.5e-4), e_i picked by ``index == i`` so that i may be a traced loop index; the quotient
    divides by the difference of the two perturbed values as rounded to the dtype."""
    xp = backend.xp
    dtype = _dtype_name(xp, o)
    x, status = hit_points(xp, o, d, t_hit)
    g, _, c1 = backend.grad_hess(scene, x, False)
    _, status = _guard(xp, status, g, d, min_cos)
    th = scene.param_vector()
    t0 = xp.where(xp.isfinite(t_hit), t_hit, xp.zeros_like(t_hit))
    newton = (status == CONV) | (status == ILL)  # non-hits stay put
    theta_b = backend.asarray(th, dtype)
    # h_i, at least √ε of the dtype relative: below it the re-solved depths' rounding (≈ ε|t|/slope)
    # is the quotient (float32 at the default h = 1e-6: dt/dθ 0.8–2.2 off on every hit, CONVERGED)
    steps_b = backend.asarray(max(h, float(np.sqrt(np.finfo(dtype).eps))) * np.maximum(1.0, np.abs(th)), dtype)
    index_b = backend.asarray(np.arange(th.size), dtype)

    tol = float(np.sqrt(np.finfo(dtype).eps))

    def column(i, carry):
        dt, cost, stuck = carry
        e_i = index_b == i
        ends = (theta_b[i] + steps_b[i], theta_b[i] - steps_b[i])  # θ_i ± h_i, rounded to the dtype
        ts = []
        for end in ends:
            ev = backend.ray_eval(scene, xp.where(e_i, end, theta_b))
            t = t0
            for _ in range(NEWTON_STEPS):
                f, df, c = ev(o, d, t, True)
                step = f / df
                t = xp.where(newton, t - step, t)
                cost = cost + c
            # Newton from t̂ converges quadratically to the moved root; a last step above √ε·|t|
            # (or none finite) means it did not: the perturbed ray misses the surface (a grazing
            # hit's neighbour) and t is no root, so the quotient is no derivative
            # (a non-finite step is φ's NaN or a zero slope: NON_FINITE, which _finish_dt gives)
            stuck = stuck | (xp.isfinite(step) & (xp.abs(step) > tol * xp.maximum(xp.abs(t), 1.0)))
            ts.append(t)
        col = (ts[0] - ts[1]) / (ends[0] - ends[1])  # the step actually taken, not 2h_i
        return xp.where(e_i[None, :], col[:, None], dt), cost, stuck

    dt0 = backend.asarray(np.zeros((o.shape[0], th.size)), dtype)
    dt, cost, stuck = backend.fori_loop(0, th.size, column, (dt0, c1, xp.zeros_like(newton)))
    status = xp.astype(xp.where(newton & stuck, ILL, status), xp.int32)
    out = _finish_dt(xp, status, dt, t_hit, cost)
    out["iterations"] = xp.full_like(out["iterations"], NEWTON_STEPS)
    return out


IMPLS = {"dt_implicit": dt_implicit, "dt_idr": dt_idr, "dt_unrolled": dt_unrolled,
         "dt_finite_diff": dt_finite_diff}


def central_jacobian(xp, fun, theta_np: np.ndarray, to_backend):
    """Central-difference Jacobian of θ ↦ (n,) with h_i = ε^{1/3}·max(1, |θ_i|), ε the run's dtype's
    (that of ``to_backend(θ)``): numpy's stand-in for forward-mode autodiff, error about ε^{2/3}
    relative (1e-10 in float64, 2e-5 in float32).  The divisor is the difference of the two
    perturbed θ_i as the backend holds them, rounded to its dtype, not 2h (in float32 θ_i ± h
    rounds by up to ε|θ_i|/2, a relative 1e-4 of 2h).  Cost: 2P calls of ``fun``.  (With float64's ε
    in a float32 run the step, 1.6e-5·max(1, |θ|), was a few float32 spacings of θ, and dt/dθ came
    out up to 13 % off on every hit of a rotated torus.)"""
    eps = float(np.finfo(np.dtype(str(to_backend(theta_np).dtype).rpartition(".")[2])).eps)
    cols = []
    for i in range(theta_np.size):
        hi = eps ** (1 / 3) * max(1.0, abs(float(theta_np[i])))
        tp, tm = theta_np.copy(), theta_np.copy()
        tp[i] += hi
        tm[i] -= hi
        TP, TM = to_backend(tp), to_backend(tm)
        step = float(TP[i]) - float(TM[i])
        with _quiet(xp):  # missed rays give inf − inf = NaN; their status says so
            cols.append((fun(TP) - fun(TM)) / step)
    return xp.stack(cols, axis=1), 2 * theta_np.size
