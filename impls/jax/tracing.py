"""Ray root finders in jax (mirror of ``impls/numpy/tracing.py``), jit-compatible.

Fixed-shape masked updates: rays are split into chunks of ``CHUNK`` and ``lax.map`` runs, per
chunk, one ``lax.while_loop`` per stage of the algorithm, so a chunk stops as soon as *its* rays
are done (a single whole-batch loop would run every ray to the slowest ray's count); the
stragglers of a capped first pass are then packed into few chunks (:func:`run_loop`).  Finished rays keep their
values (``jnp.where`` on the status).  dφ/dt = ⟨∇φ, d⟩ by ``jax.jvp`` (one evaluation).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax

from ..core import rootfind
from ..core.methods_root import make_root_finder, root_impls

CHUNK = 64


def ray_eval(backend, scene, theta=None):
    def ev(o, d, t, deriv):
        if not deriv:
            return scene.value(o + t[:, None] * d, jnp, theta), None, 1
        f, df = jax.jvp(lambda tt: scene.value(o + tt[:, None] * d, jnp, theta), (t,), (jnp.ones_like(t),))
        return f, df, 1

    return ev


CAP = 48  # first pass: at most this many steps per stage and chunk (see run_loop)
POOL_FRACTION = 16  # the straggler pass takes n/16 rays (rounded up to whole chunks)
_UNCAPPED = 2**31 - 1


def _chunked(alg, o, d, s, ev, chunk, cap):
    """Every chunk of ``chunk`` rays through the stages in order, each stage's ``lax.while_loop``
    stopping when the chunk's rays have left the stage or after ``cap`` steps.  Rays of other
    stages or finished ones are masked (keep their values)."""

    def one(args):
        oc, dc, sc = args
        for k, name in enumerate(alg.stages):
            step = getattr(alg, name)

            def active(s, k=k):
                return (s["status"] == rootfind.IN) & (s["phase"] == k)

            def body(c, step=step, active=active):
                s, i = c
                new = step(jnp, s, oc, dc, ev)
                a = active(s)
                return {key: jnp.where(a, new[key], s[key]) for key in s}, i + 1

            sc, _ = lax.while_loop(lambda c, active=active: jnp.any(active(c[0])) & (c[1] < cap), body, (sc, 0))
        return sc

    shaped = {k: v.reshape(-1, chunk) for k, v in s.items()}
    out = lax.map(one, (o.reshape(-1, chunk, 3), d.reshape(-1, chunk, 3), shaped))
    return {k: v.reshape(-1) for k, v in out.items()}


def run_loop(alg, o, d, ev, chunk=CHUNK, cap=CAP):
    """Run ``alg`` on every ray; returns the per-ray outputs.

    Per-ray step counts are heavy-tailed (grazing rays), and a chunk runs as long as its slowest
    ray.  So: (1) every chunk runs at most ``cap`` steps per stage; (2) the rays still iterating
    (gathered to the front by a stable sort, n/``POOL_FRACTION`` of them, a static size) run to
    the end packed into few chunks; (3) only if more rays than that were left does a last pass
    over all chunks finish them (``lax.cond``).  The algorithm is a per-ray state machine, so the
    results do not depend on the passes.
    """
    n = o.shape[0]
    if n == 0:
        return rootfind.outputs(alg.init(jnp, o, d, ev))
    chunk = min(chunk, n)
    pad = (-n) % chunk
    if pad:  # pad with copies of the first ray; their results are dropped
        o = jnp.concatenate([o, jnp.broadcast_to(o[:1], (pad, 3))])
        d = jnp.concatenate([d, jnp.broadcast_to(d[:1], (pad, 3))])
    m = o.shape[0]
    s = alg.init(jnp, o, d, ev)
    pool = min(m, chunk * -(-m // (POOL_FRACTION * chunk)))
    if pool >= m:  # few rays: one uncapped pass
        s = _chunked(alg, o, d, s, ev, chunk, _UNCAPPED)
    else:
        s = _chunked(alg, o, d, s, ev, chunk, cap)
        left = s["status"] == rootfind.IN
        idx = jnp.argsort(~left, stable=True)[:pool]
        sub = _chunked(alg, o[idx], d[idx], {k: v[idx] for k, v in s.items()}, ev, chunk, _UNCAPPED)
        s = {k: v.at[idx].set(sub[k]) for k, v in s.items()}
        s = lax.cond(jnp.sum(left) > pool, lambda s: _chunked(alg, o, d, s, ev, chunk, _UNCAPPED), lambda s: s, s)
    return {k: v[:n] for k, v in rootfind.outputs(s).items()}


def solve(method, backend, scene, o, d, *, t_min, t_max, theta=None, **knobs):
    alg = make_root_finder(method, scene, t_min, t_max, knobs, theta)
    return run_loop(alg, o, d, ray_eval(backend, scene, theta))


IMPLS = root_impls(solve, "jax")
sphere_trace = IMPLS["sphere_trace"]
