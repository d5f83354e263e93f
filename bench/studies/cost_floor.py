"""The floor under a certified root finder's cost: the fewest φ evaluations per ray that any method
relying only on the Lipschitz bound L could spend to certify its answer.  The bound is the one the
root finders step by: that of the scene's step field (:func:`impls.core.methods_root.step_field`,
CSG operands at their own bounds; the scene itself wherever its leaves' bounds agree).

A certified method proves "no crossing before the bracket" by unbounding spheres: a sample at t
with r = |φ(t)|/L shows no surface in [t − r, t + r].  To report CONVERGED it must cover the ray
from its start (the ray bound's entry, ``lo``) up to ``min_step`` before the first crossing t*
(:class:`impls.core.rootfind.MarchRefine`'s rule), and show one sample past t*; a certified MISS
must cover all of [lo, hi].  With φ known everywhere (an oracle), the fewest samples covering
[lo, end] is found greedily (the interval-cover greedy is optimal): from the frontier x, the next
sample is the furthest t whose sphere still reaches back to x, the root of t − |φ(t)|/L = x
(t − |φ(t)|/L is non-decreasing since |φ| is L-Lipschitz), found by bisection; the frontier moves
to t + |φ(t)|/L.  A real method also evaluates its start and refines the bracket to ``xtol``, so it
spends a few evaluations per hit more than this floor; a CONVERGED or certified MISS ray that
spent fewer than the floor would have certified what its samples cannot show.

The samples here use the exact |φ| (no rounding allowance), so the floor is slightly optimistic,
never pessimistic.  Rays whose cover does not finish within ``max_samples`` (a tangent ray: the
spheres shrink to 0) count ``max_samples``."""

from __future__ import annotations

import numpy as np

from impls.core.methods_root import step_field

#: bisection steps locating each greedy sample (the bracket starts ≤ 2·(hi − lo) wide: 60 halvings
#: place it to 2⁻⁶⁰ of that, far below min_step)
BISECTIONS = 60


def greedy_cover(scene, o: np.ndarray, d: np.ndarray, lo: np.ndarray, end: np.ndarray,
                 max_samples: int = 100_000) -> np.ndarray:
    """Per ray, the fewest samples whose unbounding spheres cover [lo, end] (0 where lo ≥ end)."""
    scene = step_field(scene)
    inv_lip = 1.0 / float(scene.info.lipschitz)
    x = lo.astype(np.float64).copy()
    count = np.zeros(len(o), dtype=np.int64)
    active = x < end
    while active.any():
        idx = np.nonzero(active)[0]
        oi, di, xi = o[idx], d[idx], x[idx]
        a, b = xi.copy(), xi + 2.0 * np.maximum(end[idx] - xi, 0.0) + 1e-300
        for _ in range(BISECTIONS):
            c = 0.5 * (a + b)
            reach_back = c - np.abs(scene.value(oi + c[:, None] * di)) * inv_lip
            inside = reach_back <= xi
            a, b = np.where(inside, c, a), np.where(inside, b, c)
        front = a + np.abs(scene.value(oi + a[:, None] * di)) * inv_lip
        count[idx] += 1
        # a frontier that no longer moves (φ = 0 at it: a tangency or the surface) never covers the rest
        stuck = (front <= xi) | (count[idx] >= max_samples)
        x[idx] = np.where(stuck, np.inf, front)
        count[idx[stuck]] = max_samples
        active = x < end
    return count


def floor_per_ray(scene, o: np.ndarray, d: np.ndarray, t_max: float, min_step: float) -> dict:
    """``{"floor", "hit", "in_bounds"}`` per ray: the oracle's samples (a hit's cover up to
    min_step before its first crossing, plus one past it; a miss's cover of its ray bound)."""
    lo, hi = scene.ray_bounds(np, o, d)
    lo, hi = np.maximum(np.asarray(lo, np.float64), 0.0), np.minimum(np.asarray(hi, np.float64), t_max)
    first = np.asarray(scene.first_hit(o, d, 0.0), np.float64)
    hit = np.isfinite(first) & (first <= hi)
    end = np.where(hit, first - min_step, hi)
    floor = greedy_cover(scene, o, d, lo, end) + hit
    return {"floor": floor, "hit": hit, "in_bounds": lo < hi}


def table(method_evals: dict, floors: dict) -> list[dict]:
    """One row per scene: the floor and a method's evaluations per ray, over all rays and hits."""
    rows = []
    for name, fl in floors.items():
        ev = np.asarray(method_evals[name], np.float64)
        hit = fl["hit"]
        rows.append({"scene": name, "rays": int(ev.size), "floor_per_ray": float(fl["floor"].mean()),
                     "evals_per_ray": float(ev.mean()), "floor_per_hit": float(fl["floor"][hit].mean()),
                     "evals_per_hit": float(ev[hit].mean())})
    return rows
