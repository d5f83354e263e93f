"""Ray root finders in jax (mirror of ``impls/numpy/tracing.py``), jit-compatible.

Fixed-shape masked updates: rays are split into chunks of ``CHUNK`` and ``lax.map`` runs, per
chunk, one ``lax.while_loop`` per stage of the algorithm, so a chunk stops as soon as *its* rays
are done (a single
whole-batch loop would run every ray to the slowest ray's count).  Finished rays keep their
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


def run_loop(alg, o, d, ev, chunk=CHUNK):
    """Run ``alg`` per chunk of rays (``lax.map`` of ``lax.while_loop``); returns the per-ray outputs."""
    n = o.shape[0]
    if n == 0:
        return rootfind.outputs(alg.init(jnp, o, d, ev))
    chunk = min(chunk, n)
    pad = (-n) % chunk
    if pad:  # pad with copies of the first ray; their results are dropped
        o = jnp.concatenate([o, jnp.broadcast_to(o[:1], (pad, 3))])
        d = jnp.concatenate([d, jnp.broadcast_to(d[:1], (pad, 3))])

    def one(args):
        oc, dc = args
        s = alg.init(jnp, oc, dc, ev)
        for k, name in enumerate(alg.stages):  # stages in order, each its own loop
            step = getattr(alg, name)

            def active(s, k=k):
                return (s["status"] == rootfind.IN) & (s["phase"] == k)

            def body(s, step=step, active=active):
                new = step(jnp, s, oc, dc, ev)
                a = active(s)
                return {key: jnp.where(a, new[key], s[key]) for key in s}

            s = lax.while_loop(lambda s, active=active: jnp.any(active(s)), body, s)
        return s

    out = lax.map(lambda a: rootfind.outputs(one(a)), (o.reshape(-1, chunk, 3), d.reshape(-1, chunk, 3)))
    return {k: v.reshape(-1)[:n] for k, v in out.items()}


def solve(method, backend, scene, o, d, *, t_min, t_max, theta=None, **knobs):
    alg = make_root_finder(method, scene, t_min, t_max, knobs)
    return run_loop(alg, o, d, ray_eval(backend, scene, theta))


IMPLS = root_impls(solve, "jax")
sphere_trace = IMPLS["sphere_trace"]
