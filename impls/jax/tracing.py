"""Ray root finders in jax (mirror of ``impls/numpy/tracing.py``), jit-compatible.

Fixed shapes, masked updates, compaction by levels (:func:`run_loop`): ``lax.map`` runs the
rays in chunks of ``CHUNK``; within a chunk every stage of the algorithm is a
``lax.while_loop`` over a batch whose rays not in that stage (or finished) keep their values
(``jnp.where`` on the status), and the batch shrinks by ``RATIO`` from level to level as rays
finish (the rays still iterating are gathered with ``jnp.nonzero(size=…)``, a static size).
dφ/dt = ⟨∇φ, d⟩ by ``jax.jvp`` (one evaluation).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax

from ..core import rootfind
from ..core.methods_root import make_root_finder, root_impls


def computed_once(fn, t):
    """``fn(t)``, computed once into buffers of its own.

    XLA's CPU compiler fuses the producers of an array into each of its consumers, so φ along
    the rays was recomputed inside every state update of a step (the march step: 6 fusions,
    each re-evaluating most of φ; torus ∪ box, 25 ns per ray and step at 4096 rays, 9 ns with
    φ computed once).  ``lax.optimization_barrier`` is removed before fusion on the CPU, so
    ``fn`` runs as the taken branch of a conditional, whose results are always materialized.
    The predicate is always true (t₀ is NaN or it is not); it is data-dependent only so that
    XLA cannot fold the conditional away."""
    if t.size == 0:
        return fn(t)
    t0 = t.reshape(-1)[0]

    def never(t):
        return jax.tree.map(lambda a: jnp.full(a.shape, jnp.nan, a.dtype), jax.eval_shape(fn, t))

    return lax.cond(jnp.isnan(t0) | ~jnp.isnan(t0), fn, never, t)


def ray_eval(backend, scene, theta=None):
    def ev(o, d, t, deriv):
        def phi(t):
            return scene.value(o + t[:, None] * d, jnp, theta)

        if not deriv:
            return computed_once(phi, t), None, 1
        f, df = computed_once(lambda t: jax.jvp(phi, (t,), (jnp.ones_like(t),)), t)
        return f, df, 1

    return ev


# Measured (bench/speed.py, torus ∪ box, 2^20 rays, hybrid_secant): a masked step costs about
# 14 ns per ray on a 2^16-ray batch and about 30 ns on a 2^20-ray one (the state no longer
# stays in cache), so chunks of 2^16; halving the batch (RATIO 2) wastes fewer masked steps
# than quartering it; below LAST rays the loop overhead dominates, so the last level runs to
# the end.
CHUNK = 1 << 16
RATIO = 2
LAST = 64


def level_sizes(m: int, ratio: int = RATIO, last: int = LAST) -> list[int]:
    """Batch sizes of the levels of a chunk of ``m`` rays: m, ⌈m/ratio⌉, … down to ``last``."""
    sizes = [m]
    while sizes[-1] > last:
        sizes.append(max(-(-sizes[-1] // ratio), last))
    return sizes


def _levels(alg, s: dict, o, d, ev, sizes: list[int]) -> dict:
    """Run the rays of state ``s`` (a batch of ``sizes[0]`` rows, rays ``o``, ``d``) to the end;
    returns their outputs (:data:`impls.core.rootfind.STATE_OUT`).

    This level's loop for stage k runs while more than ``sizes[1]``/(number of stages) rays
    are in stage k, so at most ``sizes[1]`` rays are left; they are gathered into a batch of
    that size (``jnp.nonzero`` with a static ``size``; padding rows are marked finished and
    never written back) and run by the next level, skipped (``lax.cond``) when no ray is
    left, and only their outputs are scattered back.  The last level runs every stage to the
    end.  Per-ray results do not depend on the levels: each ray's iteration is independent."""
    m = sizes[0]
    keep = sizes[1] // len(alg.stages) if len(sizes) > 1 else 0
    for k, name in enumerate(alg.stages):
        step = getattr(alg, name)

        def active(c, k=k):
            return (c["status"] == rootfind.IN) & (c["phase"] == k)

        def body(c, step=step, active=active):
            new = step(jnp, c, o, d, ev)
            a = active(c)
            return {key: jnp.where(a, new[key], c[key]) for key in c}

        s = lax.while_loop(lambda c, active=active: jnp.sum(active(c)) > keep, body, s)
    out = rootfind.outputs(s)
    if len(sizes) == 1:
        return out
    left = s["status"] == rootfind.IN

    def next_level(out):
        sel = jnp.nonzero(left, size=sizes[1], fill_value=m)[0]
        g = jnp.minimum(sel, m - 1)
        sub = {k: v[g] for k, v in s.items()}
        sub["status"] = jnp.where(sel < m, sub["status"], rootfind.CONV)  # padding: finished
        res = _levels(alg, sub, o[g], d[g], ev, sizes[1:])
        return {k: v.at[sel].set(res[k], mode="drop") for k, v in out.items()}

    return lax.cond(jnp.any(left), next_level, lambda out: out, out)


def run_loop(alg, o, d, ev, chunk: int = CHUNK, ratio: int = RATIO, last: int = LAST) -> dict:
    """Run ``alg`` on every ray; returns the per-ray outputs.

    Per-ray step counts are heavy-tailed (grazing rays need thousands of steps, most rays a
    few), and a fixed-shape loop runs as long as its slowest ray, so the rays still iterating
    are compacted into ever smaller batches (:func:`_levels`), chunk by chunk (``lax.map``
    over chunks of ``chunk`` rays keeps each chunk's state in cache).  The algorithm is a
    per-ray state machine, so the results do not depend on chunks or levels."""
    n = o.shape[0]
    if n == 0:
        return rootfind.outputs(alg.init(jnp, o, d, ev))
    chunk = min(chunk, n)
    pad = (-n) % chunk
    if pad:  # pad with copies of the first ray; their results are dropped
        o = jnp.concatenate([o, jnp.broadcast_to(o[:1], (pad, 3))])
        d = jnp.concatenate([d, jnp.broadcast_to(d[:1], (pad, 3))])
    sizes = level_sizes(chunk, ratio, last)
    out = lax.map(lambda od: _levels(alg, alg.init(jnp, od[0], od[1], ev), od[0], od[1], ev, sizes),
                  (o.reshape(-1, chunk, 3), d.reshape(-1, chunk, 3)))
    return {k: v.reshape(-1)[:n] for k, v in out.items()}


def solve(method, backend, scene, o, d, *, t_min, t_max, theta=None, **knobs):
    alg = make_root_finder(method, scene, t_min, t_max, knobs, theta)
    return run_loop(alg, o, d, ray_eval(backend, scene, theta))


IMPLS = root_impls(solve, "jax")
sphere_trace = IMPLS["sphere_trace"]
