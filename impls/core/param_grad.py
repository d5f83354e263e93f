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
  when |φ(x_steps)|/L ≤ ``UNROLLED_TOL`` (the unrolled tracer reached the surface), MISS when
  t left [t_min, t_max], else MAX_ITER (its derivative is then not dt/dθ of a hit).
* ``dt_finite_diff`` — (t(θ + h_i e_i) − t(θ − h_i e_i)) / 2h_i, h_i = h·max(1, |θ_i|), each
  t re-solved from t̂ by ``NEWTON_STEPS`` safeguard-free Newton steps (the root moves by O(h)).

Guard: where |⟨∇φ, d⟩|/|∇φ| < ``min_cos`` (grazing) the status is ILL_CONDITIONED (the value is
still returned: it is the method's answer, just not trustworthy).
"""

from __future__ import annotations

import numpy as np

from .pointwise import finish, hit_points
from .rootfind import CONV, MAXI, MISS, _quiet

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
    return gd, xp.astype(xp.where((status == CONV) & ~(xp.abs(cos) >= min_cos), ILL, status), xp.int32)


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


def dt_unrolled(backend, scene, o, d, *, t_min, t_max, t_hit, steps, min_cos):
    xp = backend.xp
    inv_lip = 1.0 / float(scene.info.lipschitz)

    def t_of(th):
        return unrolled_depth(xp, scene, o, d, t_min, steps, th, backend.fori_loop)

    th0 = theta0(backend, scene, o)
    t = t_of(th0)
    far = ~(t <= t_max)  # left the range, or NaN
    x, status = hit_points(xp, o, d, xp.where(far, xp.full_like(t, float("inf")), t))
    status = xp.astype(xp.where((status == CONV) & far, MISS, status), xp.int32)
    reached = xp.abs(scene.value(x, xp)) * inv_lip <= UNROLLED_TOL
    status = xp.astype(xp.where((status == CONV) & ~reached, MAXI, status), xp.int32)
    g, _, c1 = backend.grad_hess(scene, x, False)
    _, status = _guard(xp, status, g, d, min_cos)
    J, c2 = backend.theta_jacobian(t_of, th0)
    out = _finish_dt(xp, status, J, xp.where(far, xp.full_like(t, float("inf")), t), c1 + c2 * steps + steps + 1)
    out["iterations"] = xp.full_like(out["iterations"], steps)
    return out


def dt_finite_diff(backend, scene, o, d, *, t_min, t_max, t_hit, h, min_cos):
    xp = backend.xp
    x, status = hit_points(xp, o, d, t_hit)
    g, _, c1 = backend.grad_hess(scene, x, False)
    _, status = _guard(xp, status, g, d, min_cos)
    th = scene.param_vector()
    t0 = xp.where(xp.isfinite(t_hit), t_hit, xp.zeros_like(t_hit))
    cols, cost = [], c1
    for i in range(th.size):
        hi = h * max(1.0, abs(float(th[i])))
        ts = []
        for sgn in (1.0, -1.0):
            tp = th.copy()
            tp[i] += sgn * hi
            ev = backend.ray_eval(scene, backend.asarray(tp, _dtype_name(xp, o)))
            t = t0
            for _ in range(NEWTON_STEPS):
                f, df, c = ev(o, d, t, True)
                t = xp.where((status == CONV) | (status == ILL), t - f / df, t)  # non-hits stay put
                cost += c
            ts.append(t)
        cols.append((ts[0] - ts[1]) / (2 * hi))
    dt = xp.stack(cols, axis=1) if cols else xp.zeros_like(o[:, :0])
    out = _finish_dt(xp, status, dt, t_hit, cost)
    out["iterations"] = xp.full_like(out["iterations"], NEWTON_STEPS)
    return out


IMPLS = {"dt_implicit": dt_implicit, "dt_idr": dt_idr, "dt_unrolled": dt_unrolled,
         "dt_finite_diff": dt_finite_diff}


def central_jacobian(xp, fun, theta_np: np.ndarray, to_backend):
    """Central-difference Jacobian of θ ↦ (n,) with h_i = ε^{1/3}·max(1, |θ_i|) (numpy's stand-in for
    forward-mode autodiff; error ≈ 1e-10 relative).  Cost: 2P calls of ``fun``."""
    eps = np.finfo(np.float64).eps
    cols = []
    for i in range(theta_np.size):
        hi = eps ** (1 / 3) * max(1.0, abs(float(theta_np[i])))
        tp, tm = theta_np.copy(), theta_np.copy()
        tp[i] += hi
        tm[i] -= hi
        with _quiet(xp):  # missed rays give inf − inf = NaN; their status says so
            cols.append((fun(to_backend(tp)) - fun(to_backend(tm))) / (2 * hi))
    return xp.stack(cols, axis=1), 2 * theta_np.size
