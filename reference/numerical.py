"""The numerical reference for scenes without closed-form hits (MLP fields, user callables).

Dense bracketing plus bisection in float64, certified by a Lipschitz bound where the scene has
one:

1. Sample φ at ``n_samples`` depths on [t_min, t_max], equally spaced but for a per-ray shift
   of the interior ones (:func:`_sample_depths`).
2. An interval [a, b] without a sign change is *certified root-free* when
   |φ(a)| + |φ(b)| > L (b − a): a zero inside would need |φ(a)| ≤ L(t* − a) and
   |φ(b)| ≤ L(b − t*).  Uncertified intervals before the first sign change are halved until
   they are certified, show a sign change, or are narrower than ``min_width`` (then a possible
   tangency closer than the float64 resolution of φ; the ray's bound is NaN to say so).
3. The first sign change is bisected to adjacent floats of the float64 φ, *left half first*: at
   the midpoint m of [lo, hi], [lo, m] with a sign change → left; [lo, m] certified root-free
   (as in 2) → right; else → right, with [lo, m] kept *pending* (φ of one sign at both ends, it
   may hold an even number of crossings before the one bisected).  The pending pieces are
   subdivided as in 2; a sign change found there, before the answer, is bisected the same way, and
   so on until none is left before the answer.  (Before, the bracket was bisected blindly: a
   sample interval holding a thin shell 3e-3 before a sphere (in, out, in) gave the sphere's
   depth with a ~1e-14 bound on 11,080 of 65,536 rays.)  Beside a crossing of slope |dφ/dt| < L
   the Lipschitz cones of points y before it reach only y·|dφ/dt|/L, so the pieces next to the
   answer cannot all be certified: pieces within the ray's depth bound of the answer are not
   examined (a root there is within the bound); those subdivided down to a few ulps without being
   certified widen the bound to cover them (to at most :data:`NEAR_WIDEN` × the bound; farther
   before the answer they flag the ray, as a possible tangency).  On the catalog's MLP and neural
   cameras this costs ~13 % more evaluations of φ and changes no depth.

4. The bound is checked, not trusted: every pair of samples (and of subdivision points) with
   |φ(b) − φ(a)| > L (b − a) (beyond rounding, :func:`lipschitz_violated`) shows that the
   declared L is false on that ray; the ray is then *flagged*: t = NaN with an infinite error
   bound, since no certification that used L can stand there.
5. A bound stated on a domain only (``SceneInfo.domain``: the algebraic sphere's on |x| ≤ R,
   a neural SDF's on a box) is used, and checked, only inside the scene's ray bounds, which such
   a scene keeps inside its domain (outside them φ > 0, so nothing is missed there).  Where those
   bounds are a user's assertion, the stretches they leave out are sampled: φ ≤ 0 there refutes
   them, and no ray has an answer (:func:`_bounds_refuted`).

Certification allows for rounding: an interval counts as root-free only when
|φ(a)| + |φ(b)| − δφ(a) − δφ(b) > L (b − a), δφ the float64 φ's evaluation error
(:func:`reference.depthbound.phi_rounding`), since the real φ may be δφ nearer zero.  A ray whose
uncertified intervals exceed :data:`MAX_PENDING` (near a tangency their number grows like 1/√w
at width w) is flagged as a possible tangency, like one that reaches ``min_width``; so are the
most crowded rays of a pass whose pieces together exceed :data:`MAX_PENDING_TOTAL` (memory).
(Which rays a pass flags so depends on the pass; the per-ray cap does not.)

The scan's samples are shifted per ray (:func:`_sample_depths`): a feature narrower than the
sample spacing at the same depth on every ray no longer falls between the same two samples on
all of them.  A user's φ is evaluated twice at the first rays' samples: one that changes beyond
its rounding between evaluations is refused (:func:`_check_repeatable`).

Error bound per ray: a bound on the *depth*, |t − t*| with t* the root of the real-number φ on
the real-number ray (:mod:`reference.depthbound`): the bisection bracket widened on each side
until |φ̃| exceeds δφ there with opposite signs — about δφ/|dφ/dt| where the slope is not small,
the second-order √(2δφ/|φ''|) on grazing rays.  Where φ̃ has the same sign beyond δφ on both
sides (a near-tangent ray: float64 cannot tell a touch from a near miss) the bound is NaN: the
ray is flagged, not judged.  Without a Lipschitz bound (``lipschitz=None``) steps 2 and 4 are
skipped and step 3 bisects blindly: a crossing pair between two samples can be missed and a
bracket's later crossing taken for its first.  The depths are then given but *not* certified,
and every ray's bound, hit or miss, is NaN: no ray is judged on them (stated, never hidden;
before, they had finite bounds, and a 1e-4 shell missed between samples was charged as 15,304
false misses to correct backends).

:func:`crossings_numeric` (every crossing: the split points of the rendering integrals) runs the
same scan over the whole ray and the same bisection with the pieces on *both* sides of each step
kept pending: every crossing is found except a pair of crossings closer than a few ulps to
another crossing or to each other (the pieces there are not resolved finer).
"""

from __future__ import annotations

import copy
import dataclasses
import math
import numbers
from typing import Any, Callable

import numpy as np

from . import depthbound as _depthbound
from .code_digest import function_digest
from .rays import unit_directions, unit_tolerance
from .scene import Field, FieldError, SceneInfo, _points, check_field_output, field_label, user_defined


#: uncertified intervals one ray may have pending in the scan before it is flagged (module doc)
MAX_PENDING = 1 << 17

#: uncertified intervals all the rays of one pass (:data:`CHUNK_RAYS`) may have pending together
#: (~50 bytes each); beyond it the most crowded rays are flagged first
MAX_PENDING_TOTAL = 1 << 22

#: how far a narrow uncertified piece just before a crossing may widen that ray's bound, in
#: multiples of the bound (first_hit_numeric); one farther flags the ray
NEAR_WIDEN = 4.0


#: points per call of φ (the scan's samples, a pass's subdivision points): memory, since a field's
#: intermediates scale with the points of a call (a user's MLP of width 256 as a CallableField holds
#: 256 float64 per point per layer: 0.5 GB a call at this size, where one pass's 4,194,304 samples
#: in one call took 8.6 GB a layer and the machine's memory)
POINTS_PER_CALL = 1 << 18


def _phi_at(scene, o, d, t):
    """φ(o + t d) in float64 for rays o, d (k, 3) at depths t (k,) (points (k, 3)) or (k, m) (points
    (k, m, 3)), in calls of at most :data:`POINTS_PER_CALL` points (whole rays at a time)."""
    if t.ndim == 1:
        k, m = t.shape[0], 1
    else:
        k, m = t.shape
    step = max(1, POINTS_PER_CALL // max(m, 1))
    if k <= step:
        x = o + t[:, None] * d if t.ndim == 1 else o[:, None, :] + t[:, :, None] * d[:, None, :]
        return np.asarray(scene.value(x), np.float64)
    return np.concatenate([_phi_at(scene, o[a:a + step], d[a:a + step], t[a:a + step]) for a in range(0, k, step)])


def _phi_along(scene, o, d, rows, t):
    return _phi_at(scene, o[rows], d[rows], t)


def _phi_active(scene, o, d, rows, t, active, fill):
    """φ at ``t`` on the ``active`` entries (the bisections' unfinished brackets), ``fill`` on the
    others: a bracket at adjacent floats is not evaluated again (its value is never read: every
    update is masked by ``active``)."""
    if active.all():
        return _phi_along(scene, o, d, rows, t)
    f = np.array(fill, np.float64)
    f[active] = _phi_along(scene, o, d, rows[active], t[active])
    return f


def _bisect(scene, o, d, rows, lo, hi, f_lo):
    """Bisect brackets [lo, hi] (sign change of φ) to adjacent floats, blindly; vectorised.  What
    the search does without a Lipschitz bound (nothing can be certified: which crossing of a
    bracket holding several it lands on is not known)."""
    lo_pos = f_lo > 0
    for _ in range(2100):
        mid = lo + (hi - lo) / 2
        active = (mid != lo) & (mid != hi)
        if not active.any():
            break
        f = _phi_active(scene, o, d, rows, mid, active, f_lo)
        zero = f == 0
        same = (f > 0) == lo_pos
        lo = np.where(active & same & ~zero, mid, lo)
        hi = np.where(active & (~same | zero), mid, hi)
    return lo, hi


def lipschitz_violated(f0, f1, t0, t1, L: float, mag, gain: float = 1.0):
    """Pairs whose slope |f1 − f0|/|t1 − t0| exceeds ``L`` beyond rounding: the allowance is
    16ε·``gain``·((|f0| + |f1|)/L + |t0| + |t1| + ``mag``) on top of |t1 − t0|, ``mag`` = |o|₁ plus
    the scene's offset and extent (:func:`_magnitude`): the rounding of the point o + t d and of
    φ's intermediates; ``gain`` ≥ 1 the scene's :attr:`reference.scene.Field.rounding_gain`.  The
    root finders use the same rule (:func:`impls.core.rootfind.lipschitz_violated`, where the
    reasoning is spelled out)."""
    eps = 16.0 * gain * np.finfo(np.float64).eps
    a0, a1 = np.abs(f0), np.abs(f1)
    return np.abs(f1 - f0) / L > np.abs(t1 - t0) + eps * ((a0 + a1) / L + np.abs(t0) + np.abs(t1) + mag)


def _magnitude(scene, o):
    """|o|₁ + |centre| + radius of the scene's bounding ball (per ray; 0 for the ball without one)."""
    return _depthbound.magnitude(scene, o)


def _slack(f, t, L, mag, gain):
    """δφ, the rounding of the float64 φ (:func:`reference.depthbound.phi_rounding`)."""
    return _depthbound.phi_rounding(f, t, L, mag, gain)


def _uncertified(fa, fb, a, b, L, mag, gain):
    """Whether [a, b] (φ of one sign at both ends) is *not* certified root-free: a zero inside
    needs |φ(a)| ≤ L(t* − a) and |φ(b)| ≤ L(b − t*), so |φ(a)| + |φ(b)| > L (b − a) excludes it;
    each end's value is reduced by δφ there (the real φ can be that much nearer zero)."""
    return np.abs(fa) + np.abs(fb) - _slack(fa, a, L, mag, gain) - _slack(fb, b, L, mag, gain) <= L * (b - a)


#: the fields of a set of intervals (or brackets) of several rays, one array each: the ray, the
#: ends a < b, φ there, and the width below which an uncertified one is *narrow* (module doc)
_IV = ("r", "a", "b", "fa", "fb", "mw")


def _cat(parts):
    """Interval sets (tuples of the arrays of ``_IV``) concatenated into one."""
    parts = [p for p in parts if p[0].size]
    if not parts:
        return tuple(np.zeros(0, int if k == 0 else np.float64) for k in range(len(_IV)))
    return tuple(np.concatenate([p[k] for p in parts]) for k in range(len(_IV)))


def _take(iv, sel):
    return tuple(x[sel] for x in iv)


def _subdivide(scene, o, d, n, pend, L, mag, gain, limit, first_only, unresolved, violated):
    """Halve the uncertified intervals ``pend`` (φ of one sign at both ends, not certified
    root-free) until each piece is certified, shows a sign change (a bracket) or is narrower than
    its ``mw`` (*narrow*: a possible tangency at the resolution asked for).  Returns the brackets
    found and the narrow pieces (the caller decides what a narrow piece means), and sets
    ``violated`` on rays where a pair of points breaks the bound.  Pieces starting at or after
    ``limit[r]`` (per ray) are dropped; with ``first_only`` a bracket found lowers its ray's
    limit to its start (nothing after the first crossing matters).  A ray with more than
    :data:`MAX_PENDING` pieces pending is flagged ``unresolved``."""
    found, narrow = [], []
    while pend[0].size:
        pend = _take(pend, pend[1] < limit[pend[0]])
        if pend[0].size == 0:
            break
        r, a, b, fa, fb, mw = pend
        m = a + (b - a) / 2
        fm = _phi_along(scene, o, d, r, m)
        violated[r[lipschitz_violated(fa, fm, a, m, L, mag[r], gain)
                   | lipschitz_violated(fm, fb, m, b, L, mag[r], gain)]] = True
        nxt = []
        for lo, hi, flo, fhi in ((a, m, fa, fm), (m, b, fm, fb)):
            sc = (flo > 0) != (fhi > 0)
            if sc.any():
                found.append((r[sc], lo[sc], hi[sc], flo[sc], fhi[sc], mw[sc]))
                if first_only:
                    np.minimum.at(limit, r[sc], lo[sc])
            still = ~sc & _uncertified(flo, fhi, lo, hi, L, mag[r], gain)
            tight = still & ((hi - lo) <= mw)
            narrow.append((r[tight], lo[tight], hi[tight], flo[tight], fhi[tight], mw[tight]))
            s = still & ~tight
            nxt.append((r[s], lo[s], hi[s], flo[s], fhi[s], mw[s]))
        pend = _cat(nxt)
        # Near a tangency the uncertified set shrinks like √w while the intervals narrow like w:
        # their number grows as 1/√w.  A ray needing more than MAX_PENDING of them is flagged as
        # a possible tangency (as one reaching its narrow width is) rather than subdivided for ever.
        counts = np.bincount(pend[0], minlength=n)
        crowded = counts > MAX_PENDING
        if counts.sum() > MAX_PENDING_TOTAL:
            # memory: the most crowded rays are flagged first, until the others' pieces fit
            order = np.argsort(counts, kind="stable")[::-1]
            rest = counts.sum() - np.cumsum(counts[order])
            crowded[order[:int(np.argmax(rest <= MAX_PENDING_TOTAL)) + 1]] = True
        if crowded.any():
            unresolved |= crowded
            pend = _take(pend, ~crowded[pend[0]])
    return _cat(found), _cat(narrow)


def _ray_phase(o, d) -> np.ndarray:
    """A phase u ∈ [0, 1) per ray, a hash of the bits of its origin and direction: deterministic,
    the same whichever pass (:data:`CHUNK_RAYS`) or position the ray is taken in, and spread over
    [0, 1) for rays that differ in any bit.  (A splitmix-style mix by hand: numpy's generators
    take one seed per stream, not one per row of an array.)"""
    bits = np.ascontiguousarray(np.concatenate([o, d], axis=1), dtype=np.float64).view(np.uint64)
    h = np.full(bits.shape[0], 0x243F6A8885A308D3, np.uint64)
    for k in range(bits.shape[1]):
        h = (h ^ bits[:, k]) * np.uint64(0x9E3779B97F4A7C15)  # (wraps modulo 2⁶⁴, as meant)
        h ^= h >> np.uint64(31)
    h = (h ^ (h >> np.uint64(29))) * np.uint64(0xBF58476D1CE4E5B9)
    h ^= h >> np.uint64(32)
    return (h >> np.uint64(11)).astype(np.float64) / float(1 << 53)


def _sample_depths(t0, t1, n_samples, phase) -> np.ndarray:
    """The scan's depths (n, n_samples): t0ᵢ, the interior tᵢⱼ = t0ᵢ + (j + uᵢ − ½) h,
    j = 1 … n_samples − 2, and t1ᵢ, with h = (t1ᵢ − t0ᵢ)/(n_samples − 1) and uᵢ the ray's phase
    (:func:`_ray_phase`): the equally spaced grid shifted by up to ±h/2 per ray.  A feature of the
    field narrower than h at the same depth on every ray (a slab facing parallel rays) fell between
    the same two samples on all of them, so a steep dip there under a false declared L was stepped
    over, certified, on every ray (the 2026-12-01 probe); shifted, a ray whose sample lands in it
    sees the false bound, and the refutation voids every ray (:func:`_void_if_refuted`)."""
    n_samples = int(n_samples)
    ts = np.linspace(t0, t1, n_samples, axis=1)
    if n_samples > 2:
        h = (t1 - t0) / (n_samples - 1)
        j = np.arange(1, n_samples - 1, dtype=np.float64)
        ts[:, 1:-1] = t0[:, None] + (j[None, :] + (phase[:, None] - 0.5)) * h[:, None]
    return ts


#: rays whose scan samples are evaluated twice to check that a user's φ is repeatable
REPEAT_RAYS = 32


def _check_repeatable(scene, o, d, ts, f, live) -> None:
    """A user's φ must give the same values at the same points: the scan's samples of the first
    :data:`REPEAT_RAYS` live rays are evaluated again, and a difference beyond φ's rounding
    bound at either (2 δφ, :func:`reference.depthbound.phi_rounding` with L = 1 where none is
    declared) is a :class:`FieldError` naming the field and the largest difference.  A noisy φ (a
    random perturbation, a stochastic layer left in training mode) has no first crossing to be
    certified, and each backend would be judged against one draw of it.  Only where a node is a
    user's (:func:`reference.scene.user_defined` or ``declares_lipschitz``): the library's own are
    deterministic, and their second evaluation would only cost time."""
    nodes = list(scene.walk()) if hasattr(scene, "walk") else [scene]
    if not any(getattr(n, "declares_lipschitz", False) or user_defined(n) for n in nodes):
        return
    rows = np.flatnonzero(live)[:REPEAT_RAYS]
    if rows.size == 0:
        return
    again = _phi_at(scene, o[rows], d[rows], ts[rows])
    first = f[rows]
    L = scene.info.lipschitz if scene.info.lipschitz is not None else 1.0
    mag = _magnitude(scene, o[rows])[:, None]
    gain = _rounding_gain(scene)
    slack = _slack(first, ts[rows], float(L), mag, gain) + _slack(again, ts[rows], float(L), mag, gain)
    same = (again == first) | (np.abs(again - first) <= slack)
    if not np.all(same):
        i, j = (int(v[0]) for v in np.nonzero(~same))
        diff = np.abs(again - first)
        raise FieldError(
            f"{field_label(scene)} is not repeatable: evaluated twice at the same points it differs by up to "
            f"{float(np.nanmax(np.where(same, 0.0, diff))):.3g} (at x = "
            f"{np.array2string(o[rows[i]] + ts[rows[i], j] * d[rows[i]], precision=6)}: {float(first[i, j])!r} then "
            f"{float(again[i, j])!r}), beyond its float64 rounding; a first crossing of a field that changes between "
            "evaluations cannot be certified.  Make φ a deterministic function of x (fix its random state, put "
            "stochastic layers in evaluation mode)")


def _scan(scene, o, d, t0, t1, n_samples, lipschitz, min_width, all_crossings):
    """Brackets of sign changes per ray on [t0ᵢ, t1ᵢ] (per-ray arrays) as an interval set
    (``_IV``), the rays with an unresolved possible tangency, and the rays on which the Lipschitz
    bound was seen to be false (step 4 of the module doc).  Rays with t0ᵢ > t1ᵢ are not sampled
    (no brackets).  Without ``all_crossings`` only what lies before each ray's first sign change
    is subdivided."""
    n = o.shape[0]
    live = t0 <= t1
    ts = _sample_depths(np.where(live, t0, 0.0), np.where(live, t1, 0.0), n_samples, _ray_phase(o, d))
    f = _phi_at(scene, o, d, ts)
    bad = ~np.isfinite(f) & live[:, None]
    if bad.any():
        i, j = (int(v[0]) for v in np.nonzero(bad))
        x = o[i] + ts[i, j] * d[i]
        raise ValueError(f"{field_label(scene)} returned {f[i, j]} at x = {np.array2string(x, precision=6)} (ray {i}, "
                         f"t = {ts[i, j]:.6g}; {int(bad.any(axis=1).sum())} rays meet such points in [t_min, t_max]): "
                         "φ must be finite wherever a ray samples it; check the field there, or narrow [t_min, t_max] "
                         "to where it is defined")
    _check_repeatable(scene, o, d, ts, f, live)
    change = ((f[:, 1:] > 0) != (f[:, :-1] > 0)) & live[:, None]
    rows, cols = np.nonzero(change)
    mw = np.full(rows.size, float(min_width))
    brackets = (rows, ts[rows, cols], ts[rows, cols + 1], f[rows, cols], f[rows, cols + 1], mw)
    unresolved = np.zeros(n, bool)
    violated = np.zeros(n, bool)
    if lipschitz is not None:
        L = float(lipschitz)
        mag = _magnitude(scene, o)
        gain = _rounding_gain(scene)
        violated |= live & np.any(lipschitz_violated(f[:, :-1], f[:, 1:], ts[:, :-1], ts[:, 1:], L, mag[:, None], gain),
                                  axis=1)
        # certified root-free only beyond φ's rounding δφ (reference.depthbound): the real φ can be
        # δφ closer to zero than the float64 one at each end
        unc = (~change) & live[:, None] & _uncertified(f[:, :-1], f[:, 1:], ts[:, :-1], ts[:, 1:], L, mag[:, None], gain)
        rows, cols = np.nonzero(unc)
        pend = (rows, ts[rows, cols], ts[rows, cols + 1], f[rows, cols], f[rows, cols + 1],
                np.full(rows.size, float(min_width)))
        limit = np.full(n, np.inf)
        if not all_crossings:
            np.minimum.at(limit, brackets[0], brackets[1])
        found, narrow = _subdivide(scene, o, d, n, pend, L, mag, gain, limit, not all_crossings, unresolved, violated)
        unresolved[narrow[0]] = True
        brackets = _cat([brackets, found])
    return brackets, unresolved, violated


def _first_per_ray(iv, n):
    """The earliest interval of each ray of the set ``iv`` (a sub-set, one per ray, by start)."""
    if iv[0].size == 0:
        return iv
    order = np.lexsort((iv[1], iv[0]))
    r = iv[0][order]
    keep = np.ones(r.size, bool)
    keep[1:] = r[1:] != r[:-1]
    return _take(iv, order[keep])


def _bisect_leftmost(scene, o, d, br, L, mag, gain, violated, both_sides):
    """Bisect the brackets ``br`` (an interval set with a sign change, ``_IV``) to adjacent
    floats, choosing the *left* half whenever it may hold the first crossing: at the midpoint m of
    [lo, hi], [lo, m] with a sign change (or φ(m) = 0) → go left; [lo, m] certified root-free
    → go right; else [lo, m] has φ of one sign at both ends and may hold an even number of
    crossings: go right (a crossing lies in [m, hi]) and return [lo, m] as *pending*, to be
    subdivided by the caller (:func:`_subdivide`).  With ``both_sides`` (every crossing wanted)
    the right half [m, hi] left behind when going left is pending in the same way.  Every pair of
    points evaluated is checked against L (``violated``).  Returns (lo, hi, φ(lo), φ(hi), pending)."""
    r, lo, hi, flo, fhi, _ = br
    pend = []
    for _ in range(2100):
        mid = lo + (hi - lo) / 2
        active = (mid != lo) & (mid != hi)
        if not active.any():
            break
        f = _phi_active(scene, o, d, r, mid, active, flo)
        left = active & (((f > 0) != (flo > 0)) | (f == 0))
        right = active & ~left
        violated[r[active & (lipschitz_violated(flo, f, lo, mid, L, mag[r], gain)
                             | lipschitz_violated(f, fhi, mid, hi, L, mag[r], gain))]] = True
        unc_l = right & _uncertified(flo, f, lo, mid, L, mag[r], gain)
        # (mw: pieces this near a crossing are resolved down to a few ulps, not min_width; see
        # first_hit_numeric for what a narrow one there means)
        mw = 8.0 * np.spacing(np.maximum(np.abs(hi), 1.0))
        pend.append((r[unc_l], lo[unc_l], mid[unc_l], flo[unc_l], f[unc_l], mw[unc_l]))
        if both_sides:
            unc_r = left & (f != 0) & ((f > 0) == (fhi > 0)) & _uncertified(f, fhi, mid, hi, L, mag[r], gain)
            pend.append((r[unc_r], mid[unc_r], hi[unc_r], f[unc_r], fhi[unc_r], mw[unc_r]))
        lo, flo = np.where(right, mid, lo), np.where(right, f, flo)
        hi, fhi = np.where(left, mid, hi), np.where(left, f, fhi)
    return lo, hi, flo, fhi, _cat(pend)


def _search_range(scene, o, d, t_min, t_max, L):
    """Per-ray search interval: [t_min, t_max], clipped to the scene's ray bounds
    (:meth:`reference.scene.Field.ray_bounds`, outside which φ > 0) when its Lipschitz bound L is
    stated on a domain only (``SceneInfo.domain``) — the bound is then not relied on, nor
    checked, outside the ray bounds, which such a scene keeps inside its domain.  A ray whose
    bounds are the whole line keeps [t_min, t_max]."""
    n = o.shape[0]
    t0, t1 = np.full(n, float(t_min)), np.full(n, float(t_max))
    if L is None or scene.info.domain is None:
        return t0, t1
    lo, hi = (np.asarray(v, np.float64) for v in scene.ray_bounds(np, o, d))
    whole = np.isneginf(lo) & np.isposinf(hi)
    return np.where(whole, t0, np.maximum(t0, lo)), np.where(whole, t1, np.minimum(t1, hi))


#: samples a ray over the stretches a scene's ray bounds leave out (:func:`_bounds_refuted`)
BOUNDS_SAMPLES = 256


def _bounds_refuted(scene, o, d, t_min, t_max, t0, t1, n_samples) -> bool:
    """Whether φ ≤ 0 at a sample of [t_min, t_max] outside a ray's search range [t0, t1] (the
    scene's ray bounds, :func:`_search_range`), which the scene asserts holds every point where
    φ ≤ 0.  The search relies on that assertion (a user's ``CallableField(bounds=…)`` with a
    ``domain``): a ball that leaves out the surface made every ray a certified MISS, judged right,
    for the reference and the root finders alike (the 2026-11-30 probe).  It is checked here by
    ``n_samples`` samples a ray over what it leaves out (a sampled check: it refutes, it does not
    prove); where it is refuted, no ray has an answer (as for a refuted L).  Only where a node
    states its bounds on trust (a user's field: ``declares_lipschitz``, or a ``Field`` subclass
    defined outside ``reference``); the library's own nodes prove theirs (a neural SDF's box by
    interval bounds), and sampling the neural camera's stretches outside its box took 17 s per
    16,384 rays."""
    nodes = list(scene.walk()) if hasattr(scene, "walk") else [scene]
    if not any(getattr(n, "declares_lipschitz", False) or user_defined(n) for n in nodes):
        return False
    if np.all((t0 <= t_min) & (t1 >= t_max)):
        return False
    # (each ray's samples shifted by its phase, as the scan's are: a feature at the same depth on
    # every ray does not fall between the same samples on all of them)
    u = (np.arange(n_samples)[None, :] + _ray_phase(o, d)[:, None]) / n_samples
    for lo, hi in ((np.full_like(t0, t_min), np.minimum(t0, t_max)), (np.maximum(t1, t_min), np.full_like(t1, t_max))):
        live = hi > lo
        if not live.any():
            continue
        ts = lo[live, None] + (hi - lo)[live, None] * u[live]
        f = _phi_at(scene, o[live], d[live], ts)
        if np.any(f <= 0):
            return True
    return False


def _rounding_gain(scene) -> float:
    """The largest ``rounding_gain`` of the scene's nodes (≥ 1), as the root finders take it
    (:func:`impls.core.methods_root.rounding_gain`)."""
    return _depthbound.rounding_gain(scene)


def _check(scene, o, d, t_min, t_max, n_samples):
    if not isinstance(scene, Field):
        raise ValueError(f"scene must be a Field, got {type(scene).__name__}; wrap a function in CallableField")
    d_dtype = np.asarray(d).dtype
    o, d = _points(o, "o"), _points(d, "d")
    # the scan's Lipschitz checks and root exclusions are in t, and φ(o + t d) is L·‖d‖-Lipschitz in t:
    # with ‖d‖ = 1.5 … 10 every ray of a thin shell (400 of 400) was flagged, and a gap between two
    # samples was excluded at |φ(a)| + |φ(b)| > L·(b − a) where ‖d‖·L·(b − a) holds, not a proof.
    # Directions are unit, as the backends require (impls.base.check_rays), to the rounding of
    # their dtype (8·√3·ε); those unit only to float32's are normalised again in float64, as the
    # backends do, and t is the distance along d/‖d‖.
    d = unit_directions(d, unit_tolerance(d_dtype), "d", f"{d_dtype} directions")
    if not (math.isfinite(t_min) and math.isfinite(t_max) and t_min < t_max):
        raise ValueError(f"need finite t_min < t_max, got t_min={t_min}, t_max={t_max}: the numerical reference "
                         "samples the whole interval, so a case whose scene has no closed-form hits needs both ends "
                         "finite (t_max: the depth past which a ray counts as a miss)")
    if int(n_samples) < 2:
        raise ValueError(f"n_samples must be ≥ 2, got {n_samples}")
    return o, d


#: rays per pass of the numerical reference: its dense samples take n_samples × 3 floats a ray
#: (1024 samples: 24 kB), so a user's 1024² camera in one pass needed ~80 GB (256²: 4.7 GB RSS
#: measured); each ray's answer depends on that ray alone, so passes of this many rays give the
#: same answers in well under 1 GB (0.7 GB RSS at 256²)
CHUNK_RAYS = 4096


def _by_chunks(fn, o, d):
    """``fn(o, d)``'s per-ray outputs (arrays or lists), computed CHUNK_RAYS rays at a time."""
    parts = [fn(o[i:i + CHUNK_RAYS], d[i:i + CHUNK_RAYS]) for i in range(0, o.shape[0], CHUNK_RAYS)]
    return tuple(np.concatenate([p[k] for p in parts]) if isinstance(parts[0][k], np.ndarray)
                 else [x for p in parts for x in p[k]] for k in range(len(parts[0])))


def first_hit_numeric(scene: Field, o, d, t_min: float, t_max: float, *, lipschitz: float | None = "scene",
                      n_samples: int = 1024, min_width: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """First sign change of φ along each ray in (t_min, t_max]: ``(t, err_bound)``, ``inf`` for
    a miss (bound 0: certified when a Lipschitz bound is used), NaN bound where a possible
    tangency could not be resolved and on every ray when there is no Lipschitz bound (L None: not
    certified, so not judged), and t = NaN with an infinite bound on *every* ray once the
    Lipschitz bound was seen to be false on one (no certified answer: :func:`_void_if_refuted`).
    ``lipschitz="scene"`` takes ``scene.info.lipschitz``.  Rays are taken :data:`CHUNK_RAYS` at a
    time (memory)."""
    o, d = _check(scene, o, d, t_min, t_max, n_samples)
    if o.shape[0] > CHUNK_RAYS:
        return _void_if_refuted(*_by_chunks(
            lambda oc, dc: first_hit_numeric(scene, oc, dc, t_min, t_max, lipschitz=lipschitz, n_samples=n_samples,
                                             min_width=min_width), o, d))
    L = scene.info.lipschitz if lipschitz == "scene" else lipschitz
    min_width = 1e-12 * max(1.0, abs(t_max)) if min_width is None else float(min_width)
    t0, t1 = _search_range(scene, o, d, t_min, t_max, L)
    if _bounds_refuted(scene, o, d, t_min, t_max, t0, t1, BOUNDS_SAMPLES):
        n = o.shape[0]
        return np.full(n, np.nan), np.full(n, np.inf)
    brackets, unresolved, violated = _scan(scene, o, d, t0, t1, int(n_samples), L, min_width, False)
    n = o.shape[0]
    t = np.full(n, np.inf)
    err = np.zeros(n)
    if L is None:
        # nothing is certified: neither that no interval between samples holds a crossing nor which
        # crossing of a bracket the bisection lands on.  The depths are given, the bounds are NaN:
        # no ray is judged on them (Case.judged_mask), hit or miss.
        first = _first_per_ray(brackets, n)
        if first[0].size:
            lo, hi = _bisect(scene, o, d, first[0], first[1], first[2], first[3])
            t[first[0]] = lo + (hi - lo) / 2
        return t, np.full(n, np.nan)
    L = float(L)
    mag, gain = _magnitude(scene, o), _rounding_gain(scene)
    near = np.full(n, np.inf)  # start of the earliest narrow uncertified piece before a crossing
    todo = _first_per_ray(brackets, n)
    while todo[0].size:
        r = todo[0]
        lo, hi, _, _, pend = _bisect_leftmost(scene, o, d, todo, L, mag, gain, violated, False)
        mid = lo + (hi - lo) / 2
        t[r] = mid
        # the depth bound: the bracket widened by φ's rounding over the slope (reference.depthbound);
        # a bracket the rounding could explain away (no certified real crossing: a near-tangent
        # ray) is flagged, NaN
        w_lo, w_hi, crossing, _ = _depthbound.enclose(scene, o[r], d[r], lo, hi, L)
        e = np.where(crossing, np.maximum(mid - (lo - w_lo), (hi + w_hi) - mid), np.nan)
        err[r] = e
        # The pieces the bisection stepped over uncertified may hold a pair of crossings before
        # this one.  Those within the bound of the answer need no look (a root there is within the
        # bound of t); the others are subdivided as the scan's are, and a sign change found there is
        # the ray's new first bracket, bisected again the same way.
        limit = np.full(n, -np.inf)
        limit[r] = np.where(np.isfinite(e), mid - e, -np.inf)
        found, narrow = _subdivide(scene, o, d, n, pend, L, mag, gain, limit, True, unresolved, violated)
        np.minimum.at(near, narrow[0], narrow[1])
        todo = _first_per_ray(found, n)
    # A narrow piece (resolved down to a few ulps) still uncertified just before the answer: beside a
    # crossing whose slope is below L, the Lipschitz cones of points a distance y before it reach
    # only y·|dφ/dt|/L, so the last pieces before the bound's window cannot all be certified.  A
    # root there lies within t − a of t: the bound is widened to that, where it stays within
    # NEAR_WIDEN × the bound; a narrow piece farther before the answer is a possible tangency there,
    # and the ray is flagged as the scan flags its own.
    before = near < t
    gap = np.where(before, t - np.where(before, near, 0.0), 0.0)
    close = before & (gap <= NEAR_WIDEN * err)
    err = np.where(close, np.maximum(err, gap), err)
    unresolved |= before & ~close
    err[unresolved] = np.nan
    t[violated], err[violated] = np.nan, np.inf
    return _void_if_refuted(t, err)


def _void_if_refuted(t: np.ndarray, err: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every ray without an answer (t NaN, bound inf) where the Lipschitz bound was refuted on one
    ray (t NaN with an infinite bound).  L is one claim about the whole field: the other rays'
    scans stepped by it too, so a surface a false L let them step over is as possible there.
    (Before, only the refuting rays were voided: a thin steep wall declared with L = 1 in front of
    a sphere left 60 of 256 rays judged against the sphere behind the wall, and the root finders
    that stepped over the wall the same way scored 0 false hits there.)"""
    if np.any(np.isnan(t) & (err == np.inf)):
        return np.full_like(t, np.nan), np.full_like(err, np.inf)
    return t, err


def crossings_numeric(scene: Field, o, d, t_min: float, t_max: float, *, lipschitz: float | None = "scene",
                      n_samples: int = 1024) -> tuple[list[np.ndarray], np.ndarray]:
    """All sign changes of φ in (t_min, t_max) per ray (sorted), and each ray's largest bracket
    width; the same certification as :func:`first_hit_numeric` (and its passes of :data:`CHUNK_RAYS`
    rays), the bisection keeping the uncertified pieces on both sides of each step (module doc: a
    pair of crossings within a few ulps of another crossing can be missed).  Without a Lipschitz
    bound nothing is certified: crossings between samples, and all but one of a bracket's odd
    number, can be missed, and every width is NaN."""
    o, d = _check(scene, o, d, t_min, t_max, n_samples)
    if o.shape[0] > CHUNK_RAYS:
        out, err = _by_chunks(lambda oc, dc: crossings_numeric(scene, oc, dc, t_min, t_max, lipschitz=lipschitz,
                                                               n_samples=n_samples), o, d)
        return out, (np.full_like(err, np.inf) if np.any(err == np.inf) else err)  # (one chunk refuted L)
    L = scene.info.lipschitz if lipschitz == "scene" else lipschitz
    t0, t1 = _search_range(scene, o, d, t_min, t_max, L)
    n = o.shape[0]
    brackets, _, violated = _scan(scene, o, d, t0, t1, int(n_samples), L, 1e-12 * max(1.0, abs(t_max)), True)
    if L is None:
        r, lo, hi = brackets[0], *_bisect(scene, o, d, brackets[0], brackets[1], brackets[2], brackets[3])
    else:
        # Every bracket bisected as first_hit_numeric's, with the uncertified pieces on *both*
        # sides of each bisection step subdivided: a sample interval holding three crossings gives
        # all three.  Narrow pieces are not reported: a pair of crossings closer than a few ulps
        # to another crossing (or to each other) can be missed.
        L = float(L)
        mag, gain = _magnitude(scene, o), _rounding_gain(scene)
        parts, todo = [], brackets
        while todo[0].size:
            lo, hi, _, _, pend = _bisect_leftmost(scene, o, d, todo, L, mag, gain, violated, True)
            parts.append((todo[0], lo, hi))
            todo, _ = _subdivide(scene, o, d, n, pend, L, mag, gain, np.full(n, np.inf), False,
                                 np.zeros(n, bool), violated)
        r, lo, hi = (np.concatenate([p[k] for p in parts]) if parts else np.zeros(0, int if k == 0 else float)
                     for k in range(3))
    mid = lo + (hi - lo) / 2
    out = [np.zeros(0) for _ in range(n)]
    err = np.zeros(n)
    for k in range(n):
        sel = r == k
        if sel.any():
            out[k] = np.sort(mid[sel])
            err[k] = np.max(hi[sel] - lo[sel])
    if L is None:  # nothing certified (as first_hit_numeric's bounds): no width is a bound
        err[:] = np.nan
    err[violated] = np.inf  # the bound is false on these rays: crossings between samples may be missing
    if np.any(violated):  # and on every ray (_void_if_refuted)
        err[:] = np.inf
    return out, err


class CallableField(Field):
    """A user's scene: ``fn(x, xp) -> φ`` written with array-API calls of ``xp``.

    It states only what the user tells it: ``lipschitz`` (a valid bound, or None), whether it
    is an ``exact_sdf``; hits come from :func:`first_hit_numeric`.  ``name`` identifies it in
    case ids and messages; the content hash holds the name and :func:`function_digest` of ``fn``
    (its code, file, defaults and closure), so an edited function is another scene to every kept
    reference answer, ``--resume`` and ``bench compare``.  ``bounds = (centre, radius)``
    is an optional ball the user asserts contains every point where φ ≤ 0
    (:meth:`Field.bounding_sphere`); a wrong ball makes the root finders miss surface outside it,
    and, with a ``domain``, the reference, which samples what the ball leaves out and gives no
    answer on any ray where it finds φ ≤ 0 there (:func:`_bounds_refuted`).

    ``lipschitz`` must be a real number (int, float, a numpy real scalar; not a bool or a str),
    finite and > 0, or None; without one the reference's answers are not judged
    (:func:`first_hit_numeric`).  ``domain`` (where L holds: :attr:`reference.scene.SceneInfo.domain`)
    is part of the content hash when set.

    ``fn`` gets the points read-only (numpy: a view; a write such as ``x -= c`` is a FieldError
    naming the field, since every other node of the scene, e.g. the other operand of a Union,
    evaluates the same array) or as a copy (torch: ``x.clone()``, n × 3 values; jax arrays are
    immutable).

    ``fn`` must return one real floating value per point: an array of ``x``'s library (the
    namespace ``xp``), shape ``x.shape[:-1]``, dtype ``x.dtype`` (another floating precision is
    converted).  Anything else — a scalar, a trailing axis of length 1, an integer or complex
    array, a numpy array for torch/jax points — and any exception ``fn`` raises become a
    :class:`reference.scene.FieldError` (a ValueError) naming the field (:func:`check_field_output`).

    ``smooth=True`` states that φ is C² near its surface: the gradient methods (normals,
    curvature) then run on it, judged against ∇φ and the Hessian of ``fn`` by jax's autodiff in
    float64 (:mod:`reference.autodiff`, which checks that ``fn`` traces under ``jax.numpy`` with
    numpy's values; where it does not, those rows are skipped with the reason).

    ``params`` (a 1-D sequence of P finite numbers, or None) makes θ the field's parameters:
    ``fn`` is then called ``fn(x, xp, theta)`` with ``theta`` an array of ``x``'s library of
    shape (P,), the hit-depth derivatives dt/dθ (``dt_*`` methods) differentiate through it, and,
    with ``smooth=True``, are judged against −(∂φ/∂θ)/⟨∇φ, d⟩ by the same autodiff.  Without
    ``params`` the field has no θ and the ``dt_*`` rows are skipped."""

    kind = "callable"
    declares_lipschitz = True

    def __init__(self, fn: Callable[[Any, Any], Any], lipschitz: float | None = None, exact_sdf: bool = False,
                 name: str | None = None, domain: str | None = None, bounds=None, smooth: bool = False,
                 params=None):
        if not callable(fn):
            raise ValueError(f"fn must be callable as fn(x, xp), got {type(fn).__name__}")
        self.params = None
        if params is not None:
            try:
                th = np.array(params, dtype=np.float64)
            except (TypeError, ValueError):
                th = None
            if th is None or th.ndim != 1 or th.size == 0 or not np.all(np.isfinite(th)):
                raise ValueError(f"params must be a 1-D sequence of finite numbers (θ, passed to fn(x, xp, theta)) "
                                 f"or None; got {params!r}")
            th.setflags(write=False)
            self.params = th
        if not isinstance(smooth, (bool, np.bool_)):
            raise ValueError(f"smooth must be True or False (whether φ is C² near its surface), got {smooth!r}")
        self.smooth = bool(smooth)
        # a real number, not one that float() happens to take: "2" (a str) and True (a bool) were
        # accepted as 2.0 and 1.0, and "abc", [1.0] or 1+0j failed with float()'s message, not naming L
        if lipschitz is not None and (isinstance(lipschitz, (bool, np.bool_)) or not isinstance(lipschitz, numbers.Real)
                                      or not (math.isfinite(float(lipschitz)) and float(lipschitz) > 0)):
            raise ValueError(f"lipschitz must be a finite real number > 0 (a bound on |φ(x) − φ(y)|/|x − y|, e.g. "
                             f"lipschitz=1.0 for an exact SDF) or None (no bound: the reference's answers are then "
                             f"not judged); got {type(lipschitz).__name__} {lipschitz!r}")
        self.fn, self.lipschitz, self.exact_sdf = fn, None if lipschitz is None else float(lipschitz), bool(exact_sdf)
        self.name = name or f"{getattr(fn, '__module__', '?')}.{getattr(fn, '__qualname__', repr(fn))}"
        self.fn_digest = function_digest(fn)  # (in the content hash: a changed body is another scene)
        self.domain = domain
        self.bounds = None
        if bounds is not None:
            try:
                c, r = np.asarray(bounds[0], np.float64), float(bounds[1])
            except (TypeError, ValueError, IndexError):
                raise ValueError(f"bounds must be (centre, radius), e.g. ((0, 0, 0), 1.5); got {bounds!r}") from None
            if c.shape != (3,) or not np.all(np.isfinite(c)) or not (math.isfinite(r) and r > 0):
                raise ValueError(f"bounds must be (centre: 3 finite numbers, radius > 0); got {bounds!r}")
            self.bounds = (c, r)

    def own_params(self):
        # (a copy: θ is kept read-only, and torch warns on every tensor made from a read-only array)
        return {} if self.params is None else {"params": self.params.copy()}

    def bounding_sphere(self):
        return self.bounds

    @property
    def info(self):
        return SceneInfo(exact_sdf=self.exact_sdf, lipschitz=self.lipschitz, distance_bound=self.exact_sdf,
                         smooth=self.smooth, exact_hits=False, exact_normals=self.smooth,
                         exact_curvature=self.smooth, exact_hit_param_grad=self.smooth and self.params is not None,
                         domain=self.domain)

    def spec(self):
        s = super().spec()
        s["static"] = {"name": self.name, "lipschitz": self.lipschitz, "exact_sdf": self.exact_sdf,
                       "fn": self.fn_digest}
        if self.bounds is not None:
            s["static"]["bounds"] = [self.bounds[0].tolist(), self.bounds[1]]
        if self.smooth:  # (only when set: a field built before the flag keeps its content hash)
            s["static"]["smooth"] = True
        if self.domain is not None:  # (it decides where L is relied on: another domain, other answers;
            s["static"]["domain"] = self.domain  # only when set, as smooth, so older hashes stand)
        return s

    def _derivatives(self, x, hessian: bool):
        """``(φ, ∇φ, H or None, ∂φ/∂θ or None)`` at points ``x``: φ by ``value`` (numpy, checked),
        the derivatives by jax's autodiff of ``fn`` (:func:`reference.autodiff.derivatives`)."""
        if not self.smooth:
            raise NotImplementedError(f"{field_label(self)} is not declared smooth (CallableField(..., smooth=True) "
                                      "states that φ is C² near its surface)")
        from .autodiff import derivatives

        x = _points(x)
        phi = np.asarray(self.value(x), np.float64)
        return (phi, *derivatives(self.fn, x, phi, field_label(self), hessian=hessian, theta=self.params))

    def _jet(self, x):
        """φ (float64 numpy), and ∇φ and ∂φ/∂θ by jax's autodiff of ``fn`` (:mod:`reference.autodiff`)."""
        phi, g, _, dtheta = self._derivatives(x, hessian=False)
        return phi, g, np.zeros((x.shape[0], 0)) if dtheta is None else dtheta

    def curvatures_exact(self, x):
        """Principal curvatures from ∇φ and the Hessian by jax's autodiff of ``fn``
        (:func:`reference.curvature.principal_from_hessian`)."""
        from .curvature import principal_from_hessian

        _, g, h, _ = self._derivatives(x, hessian=True)
        return principal_from_hessian(g, h)

    def _eval(self, x, xp, cursor):
        # The user's function is the one place where φ can come back malformed: check it here (not
        # only in Field.value) so that a CallableField inside CSG or a transform is checked too, and
        # name the field when the function raises (else the error points into a root finder).
        # The points are shared: the other operand of a Union (any CSG node, the reference's own
        # arrays) evaluates the same x, so a function writing into it (x -= c) corrupted the scene for
        # everyone after it.  numpy: a read-only view (no copy; a write raises, named below); torch:
        # a clone (n × 3 values, cheaper than any field's own arithmetic on them, and differentiable,
        # so autograd through x is unchanged); jax arrays cannot be written.
        if isinstance(x, np.ndarray):
            x = x.view()
            x.flags.writeable = False
        elif type(x).__module__.split(".")[0] == "torch":
            x = x.clone()
        try:
            out = self.fn(x, xp) if self.params is None else self.fn(x, xp, cursor.take(self.params.copy()))
        except FieldError:
            raise
        except ValueError as exc:
            if isinstance(x, np.ndarray) and "read-only" in str(exc):
                raise FieldError(f"{field_label(self)} wrote into its input x ({type(exc).__name__}: {exc}): fn must "
                                 "not modify x in place, since the same points are evaluated by the rest of the "
                                 "scene (e.g. the other operand of a Union); compute a new array (x - c, not "
                                 "x -= c)") from exc
            raise self._raised(x, exc) from exc
        except (Exception, SystemExit) as exc:  # (a field's sys.exit() is its failure, not the caller's exit)
            raise self._raised(x, exc) from exc
        return check_field_output(self, x, out, xp)

    def _raised(self, x, exc) -> FieldError:
        call = "fn(x, xp)" if self.params is None else "fn(x, xp, theta)"
        return FieldError(f"{field_label(self)} raised {type(exc).__name__}: {exc} (evaluating {call} at "
                          f"points x of shape {tuple(getattr(x, 'shape', ()))}, {type(x).__module__.split('.')[0]} "
                          f"arrays; compute with the namespace xp it is given)")

    def _rebuild(self, own, children):
        if self.params is None:
            return self
        new = copy.copy(self)  # the same function and declarations (a subclass stays itself), another θ
        th = np.array(own["params"], dtype=np.float64).reshape(self.params.shape)
        th.setflags(write=False)
        new.params = th
        return new

    def first_hit(self, o, d, t_min: float = 0.0, t_max: float = 1e3):
        return first_hit_numeric(self, o, d, t_min, t_max)[0]
