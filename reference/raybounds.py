"""Conservative ray bounds: per ray, an interval of t outside which φ(o + t d) > 0.

:meth:`reference.scene.Field.ray_bounds` returns, for rays o + t d with |d| = 1, arrays
``(lo, hi)`` such that every t with φ(o + t d) ≤ 0 lies in [lo, hi]; an empty bound is
lo = +inf, hi = −inf, an unbounded one −inf, +inf.  With that encoding a union's bound is
(min lo, max hi) and an intersection's (max lo, min hi), with no special cases.  The root
finders search only inside the bound (:func:`impls.core.rootfind.clip_to_bounds`): a ray whose
bound is empty is a MISS at once, and the others start at lo and stop at hi.

The helpers here are written with array-API operations (numpy, torch, jax, under jit too) and
pad each shape so that rounding never cuts a crossing away: a shape of size s (its bounding
radius) grows by 1e-6·s + 32ε(|o| + s) in position, ε of the working dtype and |o| the
distance of the ray's origin from the shape's frame.  The computed end points are off by a few
ε(|o| + s) in position (the chord of a ball or slab through points of that magnitude), so the
padded bound still contains every point of the solid.

In a dtype narrower than float64 the rays themselves are rounded: the harness's rays are float64
and a float32 run sees o rounded by up to ε|o|/2 per component in the *scene's* frame, and a
transform's change of frame rounds by ε(|o| + |translation|).  Neither is seen by a leaf, whose
|o| is its own frame's: a shape far from the scene's origin, seen from close by, has a small pad
and large rounded coordinates.  So while :func:`scene_rays` is in force (the root finders'
:func:`impls.core.rootfind.clip_to_bounds` puts it there), every pad in such a dtype grows by
4ε·max|o|₁ over the rays given in the scene's frame: eight times the origins' rounding, which
also covers a change of frame for a shape near the rays, and no more, since a start moved
further before the surface than that lands where φ's rounding leaves a float32 ray unproved.
float64 runs take their rays unrounded, and there the 1e-6·s term covers a change of frame for
shapes not smaller than about 1e-9 times their distance from the scene's origin.
"""

from __future__ import annotations

import contextlib
import contextvars
import math
from typing import Any

import numpy as np

from .arrays import const, norm, sum_last


#: max |o|₁ of the rays in the scene's frame, while :func:`scene_rays` is in force in a dtype
#: narrower than float64 (a scalar of the rays' namespace: traced under jit), else None
_SCENE_FRAME: contextvars.ContextVar = contextvars.ContextVar("isobench_raybounds_scene_frame", default=None)


@contextlib.contextmanager
def scene_rays(xp: Any, o: Any):
    """Compute a scene's bounds for rays whose origins ``o`` are in the scene's frame: in a dtype
    narrower than float64, every :func:`pad` inside grows by the rounding of those origins and
    of the changes of frame below them (the module's docstring).  A context variable, not an
    argument, so that every node's ``ray_bounds`` (a user's too) keeps its signature."""
    narrow = float(xp.finfo(o.dtype).eps) > 1e-10
    frame = None
    if narrow:
        # over the rays with finite origins: one NaN origin (a BAD_INPUT ray) made every ray's
        # padding NaN, and every ray of a float32 call a certified MISS (probe of 2026-11-30)
        m = sum_last(xp, xp.abs(o))
        frame = xp.max(xp.where(xp.isfinite(m), m, xp.zeros_like(m)))
    token = _SCENE_FRAME.set(frame)
    try:
        yield
    finally:
        _SCENE_FRAME.reset(token)


def pad(xp: Any, o: Any, size: float) -> Any:
    """Per-ray padding, in position, of a shape of size ``size`` seen from origins ``o`` (in the
    shape's frame), with the scene frame's rounding under :func:`scene_rays`."""
    eps = float(xp.finfo(o.dtype).eps)
    out = 1e-6 * size + 32 * eps * (norm(xp, o) + size)
    frame = _SCENE_FRAME.get()
    return out if frame is None else out + 4 * eps * frame


def unbounded_like(xp: Any, o: Any) -> tuple[Any, Any]:
    """The whole line (−inf, +inf) for every ray."""
    return xp.full_like(o[..., 0], -math.inf), xp.full_like(o[..., 0], math.inf)


def ball_chord(xp: Any, o: Any, d: Any, centre, radius: float) -> tuple[Any, Any]:
    """Chord of the ray through the ball (centre, radius + pad): t_c ± √(R² − |p|²) with
    w = c − o, t_c = ⟨w, d⟩ and p = w − t_c d computed directly (|w|² − t_c² cancels for distant
    origins); empty when the ray misses."""
    return _chord(xp, const(xp, o, centre) - o, d, radius)


def _chord(xp: Any, w: Any, d: Any, radius: Any) -> tuple[Any, Any]:
    """:func:`ball_chord` from w = c − o (shape (..., 3), d broadcast against it) and the radius
    (a number, or an array broadcast against w's rows)."""
    tc = sum_last(xp, w * d)
    p = w - tc[..., None] * d
    rad = radius + pad(xp, w, radius)
    q = rad * rad - sum_last(xp, p * p)
    through = q >= 0
    half = xp.sqrt(xp.where(through, q, 0.0))
    return xp.where(through, tc - half, math.inf), xp.where(through, tc + half, -math.inf)


def balls_chord_hull(xp: Any, o: Any, d: Any, centres, radii) -> tuple[Any, Any]:
    """The hull of the chords of k balls (``centres`` (k, 3), ``radii`` (k,), numbers), each
    computed and padded as :func:`ball_chord` computes one, as (n, k) computations: a union of
    many children bounded by their balls costs one vectorized expression, not k of them (XLA
    inlined k chords into every use of the bound: a union of 100 spheres compiled for 91 s).
    Outside jit the balls go in blocks of at most :data:`BALLS_BLOCK` (n, k) entries (1024² rays
    and 100 balls would be 2.5 GB per (n, k, 3) temporary); min and max are exact, so the blocks
    change nothing."""
    centres = np.asarray(centres, np.float64).reshape(-1, 3)
    radii = np.asarray(radii, np.float64).reshape(-1)
    n = int(np.prod(o.shape[:-1]))
    step = len(radii) if getattr(xp, "__name__", "") == "jax.numpy" else max(1, BALLS_BLOCK // max(n, 1))
    lo = hi = None
    for i in range(0, len(radii), step):
        a, b = _chord(xp, const(xp, o, centres[i:i + step]) - o[..., None, :], d[..., None, :],
                      const(xp, o[..., 0], radii[i:i + step]))
        a, b = xp.min(a, axis=-1), xp.max(b, axis=-1)
        lo, hi = (a, b) if lo is None else (xp.minimum(lo, a), xp.maximum(hi, b))
    return lo, hi


#: (n, k) entries per block of :func:`balls_chord_hull` outside jit
BALLS_BLOCK = 1 << 22


def slab_chord(xp: Any, o: Any, d: Any, axis: int, half_width: float, size: float, padding: Any = None
               ) -> tuple[Any, Any]:
    """Interval of t with |o_axis + t d_axis| ≤ half_width + pad (``size`` sets the pad, or
    ``padding`` gives it precomputed): the two plane crossings in order, or the whole line /
    nothing for a ray parallel to the slab.  "Parallel" includes every d_axis so small that the
    crossings would overflow (|t| beyond the largest float): those are handled without dividing."""
    oa, da = o[..., axis], d[..., axis]
    h = half_width + (pad(xp, o, size) if padding is None else padding)
    aoa = xp.abs(oa)
    flat = xp.abs(da) < (aoa + h) * (1.0 / float(xp.finfo(o.dtype).max))
    safe = xp.where(flat, 1.0, da)
    t1, t2 = (-h - oa) / safe, (h - oa) / safe
    inf = xp.full_like(oa, math.inf)
    whole = xp.where(aoa <= h, inf, -inf)  # a parallel ray: hi = +inf inside, −inf outside; lo = −hi
    return xp.where(flat, -whole, xp.minimum(t1, t2)), xp.where(flat, whole, xp.maximum(t1, t2))


def box_chord(xp: Any, o: Any, d: Any, half_size, size: float) -> tuple[Any, Any]:
    """Interval of t inside the origin-centred box |x_i| ≤ half_size_i (+ pad): the
    intersection of three slabs (Kay and Kajiya's slab test), padded alike (one pad)."""
    padding = pad(xp, o, size)
    return meet(xp, *(slab_chord(xp, o, d, i, float(b), size, padding) for i, b in enumerate(half_size)))


def meet(xp: Any, *bounds) -> tuple[Any, Any]:
    """Intersection of bounds: (max lo, min hi), made the canonical empty (+inf, −inf) where
    lo > hi (so that a hull over it drops it)."""
    lo, hi = bounds[0]
    for a, b in bounds[1:]:
        lo, hi = xp.maximum(lo, a), xp.minimum(hi, b)
    none = ~(lo <= hi)
    return xp.where(none, math.inf, lo), xp.where(none, -math.inf, hi)


def hull(xp: Any, *bounds) -> tuple[Any, Any]:
    """Smallest interval containing every bound: (min lo, max hi); empty bounds drop out because
    every bound here is empty only as (+inf, −inf) (:func:`meet` makes it so)."""
    lo, hi = bounds[0]
    for a, b in bounds[1:]:
        lo, hi = xp.minimum(lo, a), xp.maximum(hi, b)
    return lo, hi
