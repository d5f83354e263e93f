"""A bound on the error of a reference hit *depth*, stated per ray.

A reference depth t̂ is computed from the float64 φ (bisection to adjacent floats of its sign
change, or a closed form polished on it).  What is wanted is the root t* of the real-number φ
along the real-number ray o + t d (o, d the float64 inputs, exact).  The float64 φ differs from
it by the evaluation error

    δφ(t) = 16 ε g (|φ̃(t)| + L (|t| + m)),                                         (1)

ε = 2⁻⁵², g ≥ 1 the scene's rounding gain (:attr:`reference.scene.Field.rounding_gain`), L its
Lipschitz bound (the rounding of the point o + t d, ≤ ε(|o| + |t|) per coordinate, moves φ by at
most L times it) and m = |o|₁ + |centre| + radius of the scene's bounding ball (the magnitudes
φ's intermediates carry).  This is the rounding model of the Lipschitz check
(:func:`reference.numerical.lipschitz_violated`, :func:`impls.core.rootfind.lipschitz_violated`).

**The enclosure.**  If φ̃(a) > δφ(a) and φ̃(b) < −δφ(b) (or the reverse), the real φ has
opposite signs at a and b, so (φ continuous) a real root lies in [a, b].  Starting from the
bracket [lo, hi] of t̂ (lo = hi = t̂ for a closed form), the offsets w = δφ/L · 2ᵏ,
k = 0, 1, …, are tried on each side until |φ̃| exceeds δφ there; the depth bound is

    |t̂ − t*| ≤ max(t̂ − (lo − w₋), (hi + w₊) − t̂).                                 (2)

Where the slope s = |dφ/dt| at the root is not small, w± ≈ δφ/s: the first-order bound
δφ/|dφ/dt| (the depth's own condition number, as in Higham, *Accuracy and Stability of
Numerical Algorithms*, 2nd ed., §1.6 / §26 on root conditioning).  Where it is small (grazing
rays) the doubling goes on until the curvature of φ lifts it above δφ: a second-order bound
w ≈ √(2δφ/|φ''|) that needs no estimate of the slope or the curvature, since only the signs of
evaluated φ̃ are used.

**Tangency.**  If φ̃ has the *same* sign beyond δφ on both sides (a tangent or near-tangent
ray: φ̃ dips within δφ of zero, or changes sign twice inside the window), the real φ need not
vanish there at all: float64 cannot tell a touch from a near miss.  Such a depth is reported
with ``crossing = False``; the numerical reference flags it (bound NaN, the ray is not judged).
A closed form keeps it with the bound (2) where exact rational arithmetic on the float64 inputs
proves that a real root exists (:meth:`reference.scene.Field.certified_roots`: the sphere's
discriminant ≥ 0, the torus's exact tangents in the planes z = ±r): the real φ vanishes there, so
|φ̃| ≤ δφ at the root, which lies in the window.  A window wider than ``max_width`` is also reported as not found.

This bound covers the depth of *a* real root within (2); that it is the *first* one rests on
the search that found t̂ (the certified scan of :mod:`reference.numerical`, or the closed form).
"""

from __future__ import annotations

import math

import numpy as np

EPS = float(np.finfo(np.float64).eps)


def rounding_gain(scene) -> float:
    """The largest ``rounding_gain`` of the scene's nodes (≥ 1), as the root finders take it
    (:func:`impls.core.methods_root.rounding_gain`)."""
    gains = [float(getattr(node, "rounding_gain", 1.0)) for node in scene.walk()]
    return max([1.0, *(g for g in gains if math.isfinite(g))])


def magnitude(scene, o: np.ndarray) -> np.ndarray:
    """|o|₁ + |centre| + radius of the scene's bounding ball, per ray (the ball's part is 0
    without one)."""
    ball = scene.bounding_sphere()
    extra = 0.0 if ball is None else float(np.linalg.norm(np.asarray(ball[0], np.float64)) + float(ball[1]))
    return np.sum(np.abs(o), axis=1) + (extra if math.isfinite(extra) else 0.0)


def phi_rounding(phi, t, L: float, mag, gain: float):
    """δφ of (1): the bound on |φ̃ − φ| at depth ``t`` of a ray with magnitude ``mag``."""
    return 16.0 * EPS * gain * (np.abs(phi) + L * (np.abs(t) + mag))


def _phi(scene, o, d, t):
    return np.asarray(scene.value(o + t[:, None] * d), np.float64)


def enclose(scene, o, d, lo, hi, L: float, *, max_width=None, max_doublings: int = 200):
    """Per ray (rows of ``o``, ``d``) with a reference depth in the bracket [``lo``, ``hi``]
    (equal for a point answer): ``(w_minus, w_plus, crossing, found)``.

    ``w_minus``/``w_plus`` are the offsets beyond ``lo``/``hi`` at which |φ̃| first exceeds δφ
    (module doc); ``crossing``: φ̃ there has opposite signs, so a real root lies in
    [lo − w₋, hi + w₊]; ``found``: both offsets were found within ``max_width`` (default
    1e-3 (|t| + m)), else the offsets are inf."""
    o, d = np.asarray(o, np.float64), np.asarray(d, np.float64)
    lo, hi = np.asarray(lo, np.float64).copy(), np.asarray(hi, np.float64).copy()
    n = o.shape[0]
    L = float(L)
    mag = magnitude(scene, o)
    gain = rounding_gain(scene)
    cap = 1e-3 * (np.abs(hi) + mag) if max_width is None else np.broadcast_to(np.asarray(max_width, np.float64), (n,))
    out_w, out_s = [], []
    for side, base in ((-1.0, lo), (1.0, hi)):
        w0 = phi_rounding(0.0, base, L, mag, gain) / L  # |φ| ≤ δ within δ/L of a root: nothing to see closer
        w = w0.copy()
        wf = np.full(n, np.inf)
        sf = np.zeros(n)
        pend = np.arange(n)
        for _ in range(max_doublings):
            if pend.size == 0:
                break
            t = base[pend] + side * w[pend]
            f = _phi(scene, o[pend], d[pend], t)
            beyond = np.abs(f) > phi_rounding(0.0, t, L, mag[pend], gain) + 16.0 * EPS * gain * np.abs(f)
            done = pend[beyond]
            wf[done], sf[done] = w[done], np.sign(f[beyond])
            rest = pend[~beyond]
            w[rest] *= 2.0
            pend = rest[w[rest] <= cap[rest]]
        out_w.append(wf)
        out_s.append(sf)
    found = np.isfinite(out_w[0]) & np.isfinite(out_w[1])
    crossing = found & (out_s[0] * out_s[1] < 0)
    return out_w[0], out_w[1], crossing, found


def depth_bounds(scene, o, d, t, L: float | None = None, *, touch_ok=None, max_width=None) -> np.ndarray:
    """Per-ray bound (2) on |t − t*| for reference depths ``t`` (a closed form's): 0 at a miss
    (t = inf; the miss is the reference's own claim), inf where t is NaN (no answer), NaN where
    float64 cannot certify a real crossing near t (a tangent or near-tangent ray: not judged)
    unless ``touch_ok`` (bool per ray) says the reference asserts a double root there, in which
    case the width of the window where |φ̃| ≤ δφ bounds it.  ``L`` defaults to the scene's
    Lipschitz bound (1 when it states none: the rounding model then is a scale, not a proof)."""
    o, d = np.asarray(o, np.float64), np.asarray(d, np.float64)
    t = np.asarray(t, np.float64)
    if L is None:
        L = scene.info.lipschitz if scene.info.lipschitz is not None else 1.0
    out = np.where(np.isnan(t), np.inf, 0.0)
    hit = np.flatnonzero(np.isfinite(t))
    if hit.size:
        wm, wp, crossing, found = enclose(scene, o[hit], d[hit], t[hit], t[hit], L, max_width=max_width)
        b = np.maximum(wm, wp)
        touch = np.zeros(hit.size, bool)
        if touch_ok is not None:
            touch = np.asarray(touch_ok, bool)[hit]
        else:  # what the scene proves in exact arithmetic (Field.certified_roots), asked only where needed
            ask = np.flatnonzero(found & ~crossing)
            if ask.size:
                touch[ask] = scene.certified_roots(o[hit[ask]], d[hit[ask]])
        out[hit] = np.where(crossing | (found & touch), b, np.nan)
    return out
