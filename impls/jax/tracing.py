"""Ray root finders in jax (mirror of ``impls/numpy/tracing.py``), jit-compatible.

Fixed-shape masked updates inside ``lax.while_loop``: finished rays keep their values while
the others iterate; the loop ends when no ray is active or the budget is spent.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import lax

from ..protocol import Status


def sphere_trace(backend, scene, o, d, *, t_min, t_max, t_hit, tol, max_steps):
    """Sphere tracing t ← t + |φ|/L; contract as in the numpy module."""
    n = o.shape[0]
    inv_lip = 1.0 / scene.info.lipschitz
    IN, CONV, MISS, MAXI, NONF, BAD = (int(s) for s in (Status.IN_PROGRESS, Status.CONVERGED, Status.MISS,
                                                         Status.MAX_ITER, Status.NON_FINITE, Status.BAD_INPUT))
    bad = ~(jnp.all(jnp.isfinite(o), axis=1) & jnp.all(jnp.isfinite(d), axis=1))
    t0 = jnp.full((n,), t_min, dtype=o.dtype)
    status0 = jnp.where(bad, BAD, IN).astype(jnp.int32)
    f0 = scene.value(o + t0[:, None] * d, jnp)
    state = (t0, f0, status0, jnp.zeros(n, jnp.int32), jnp.ones(n, jnp.int32))

    def classify(t, f, status, iters):
        active = status == IN
        af = jnp.abs(f)
        status = jnp.where(active & (af <= tol), CONV, status)
        status = jnp.where(active & ~jnp.isfinite(f), NONF, status)
        status = jnp.where((status == IN) & (iters >= max_steps), MAXI, status)
        t = jnp.where(status == NONF, jnp.nan, t)
        return t, status

    def cond(state):
        t, f, status, iters, evals = state
        _, status = classify(t, f, status, iters)
        return jnp.any(status == IN)

    def body(state):
        t, f, status, iters, evals = state
        t, status = classify(t, f, status, iters)
        active = status == IN
        t_new = jnp.where(active, t + jnp.abs(f) * inv_lip, t)
        out = active & (t_new > t_max)
        status = jnp.where(out, MISS, status)
        t_new = jnp.where(out, jnp.inf, t_new)
        stepping = active & ~out
        f_new = scene.value(o + jnp.where(stepping, t_new, t_min)[:, None] * d, jnp)
        f = jnp.where(stepping, f_new, f)
        return t_new, f, status, iters + active, evals + stepping

    t, f, status, iters, evals = lax.while_loop(cond, body, state)
    t, status = classify(t, f, status, iters)
    return {"t": t, "status": status, "iterations": iters, "evals": evals}
