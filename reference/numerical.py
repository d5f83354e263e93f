"""The numerical reference for scenes without closed-form hits (MLP fields, user callables).

Dense bracketing plus bisection in float64, certified by a Lipschitz bound where the scene has
one:

1. Sample φ at ``n_samples`` equally spaced depths on [t_min, t_max].
2. An interval [a, b] without a sign change is *certified root-free* when
   |φ(a)| + |φ(b)| > L (b − a): a zero inside would need |φ(a)| ≤ L(t* − a) and
   |φ(b)| ≤ L(b − t*).  Uncertified intervals before the first sign change are halved until
   they are certified, show a sign change, or are narrower than ``min_width`` (then a possible
   tangency closer than the float64 resolution of φ; the ray's bound is NaN to say so).
3. The first sign change is bisected to adjacent floats of the float64 φ.

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
at width w) is flagged as a possible tangency, like one that reaches ``min_width``.

Error bound per ray: a bound on the *depth*, |t − t*| with t* the root of the real-number φ on
the real-number ray (:mod:`reference.depthbound`): the bisection bracket widened on each side
until |φ̃| exceeds δφ there with opposite signs — about δφ/|dφ/dt| where the slope is not small,
the second-order √(2δφ/|φ''|) on grazing rays.  Where φ̃ has the same sign beyond δφ on both
sides (a near-tangent ray: float64 cannot tell a touch from a near miss) the bound is NaN: the
ray is flagged, not judged.  Without a Lipschitz bound (``lipschitz=None``) step 2 is skipped,
an interval narrower than the sample spacing can be missed, and the rounding model takes L = 1:
the result is then *not* certified (stated, never hidden).
"""

from __future__ import annotations

import copy
import dataclasses
import math
from typing import Any, Callable

import numpy as np

from . import depthbound as _depthbound
from .code_digest import function_digest
from .rays import unit_directions, unit_tolerance
from .scene import Field, FieldError, SceneInfo, _points, check_field_output, field_label, user_defined


#: uncertified intervals one ray may have pending in the scan before it is flagged (module doc)
MAX_PENDING = 1 << 15


def _phi_along(scene, o, d, rows, t):
    return np.asarray(scene.value(o[rows] + t[:, None] * d[rows]), np.float64)


def _bisect(scene, o, d, rows, lo, hi, f_lo):
    """Bisect brackets [lo, hi] (sign change of φ) to adjacent floats; vectorised."""
    lo_pos = f_lo > 0
    for _ in range(2100):
        mid = lo + (hi - lo) / 2
        active = (mid != lo) & (mid != hi)
        if not active.any():
            break
        f = _phi_along(scene, o, d, rows, mid)
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


def _scan(scene, o, d, t0, t1, n_samples, lipschitz, min_width, all_crossings):
    """Brackets of sign changes per ray on [t0ᵢ, t1ᵢ] (per-ray arrays), the rays with an
    unresolved possible tangency, and the rays on which the Lipschitz bound was seen to be false
    (step 4 of the module doc).  Rays with t0ᵢ > t1ᵢ are not sampled (no brackets)."""
    n = o.shape[0]
    live = t0 <= t1
    ts = np.linspace(np.where(live, t0, 0.0), np.where(live, t1, 0.0), n_samples, axis=1)  # (n, n_samples)
    f = np.asarray(scene.value(o[:, None, :] + ts[:, :, None] * d[:, None, :]), np.float64)
    bad = ~np.isfinite(f) & live[:, None]
    if bad.any():
        i, j = (int(v[0]) for v in np.nonzero(bad))
        x = o[i] + ts[i, j] * d[i]
        raise ValueError(f"{field_label(scene)} returned {f[i, j]} at x = {np.array2string(x, precision=6)} (ray {i}, "
                         f"t = {ts[i, j]:.6g}; {int(bad.any(axis=1).sum())} rays meet such points in [t_min, t_max]): "
                         "φ must be finite wherever a ray samples it; check the field there, or narrow [t_min, t_max] "
                         "to where it is defined")
    change = ((f[:, 1:] > 0) != (f[:, :-1] > 0)) & live[:, None]
    brackets = [[] for _ in range(n)]  # (a, b, f(a)) per ray
    for i, j in zip(*np.nonzero(change)):
        brackets[i].append((ts[i, j], ts[i, j + 1], f[i, j]))
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
        slack = _slack(f, ts, L, mag[:, None], gain)
        unc = (~change) & live[:, None] & (np.abs(f[:, 1:]) + np.abs(f[:, :-1]) - slack[:, 1:] - slack[:, :-1]
                                           <= L * (ts[:, 1:] - ts[:, :-1]))
        rows, cols = np.nonzero(unc)
        pend = (rows, ts[rows, cols], ts[rows, cols + 1], f[rows, cols], f[rows, cols + 1])
        while pend[0].size:
            r, a, b, fa, fb = pend
            first = np.array([min((x[0] for x in brackets[k]), default=np.inf) for k in range(n)])
            keep = (a < first[r]) | all_crossings
            r, a, b, fa, fb = r[keep], a[keep], b[keep], fa[keep], fb[keep]
            if r.size == 0:
                break
            m = a + (b - a) / 2
            fm = _phi_along(scene, o, d, r, m)
            violated[r[lipschitz_violated(fa, fm, a, m, L, mag[r], gain)
                       | lipschitz_violated(fm, fb, m, b, L, mag[r], gain)]] = True
            nxt = []
            for lo, hi, flo, fhi in ((a, m, fa, fm), (m, b, fm, fb)):
                sc = (flo > 0) != (fhi > 0)
                for k in np.flatnonzero(sc):
                    brackets[r[k]].append((lo[k], hi[k], flo[k]))
                still = ~sc & (np.abs(flo) + np.abs(fhi) - _slack(flo, lo, L, mag[r], gain)
                               - _slack(fhi, hi, L, mag[r], gain) <= L * (hi - lo))
                narrow = still & ((hi - lo) <= min_width)
                unresolved[r[narrow]] = True
                s = still & ~narrow
                nxt.append((r[s], lo[s], hi[s], flo[s], fhi[s]))
            pend = tuple(np.concatenate([x[i] for x in nxt]) for i in range(5))
            # Near a tangency the uncertified set shrinks like √w while the intervals narrow like w:
            # their number grows as 1/√w.  A ray needing more than MAX_PENDING of them is flagged as
            # a possible tangency (as one reaching min_width is) rather than subdivided for ever.
            crowded = np.bincount(pend[0], minlength=n) > MAX_PENDING
            if crowded.any():
                unresolved |= crowded
                keep = ~crowded[pend[0]]
                pend = tuple(x[keep] for x in pend)
    return brackets, unresolved, violated


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
    u = (np.arange(n_samples) + 0.5) / n_samples
    for lo, hi in ((np.full_like(t0, t_min), np.minimum(t0, t_max)), (np.maximum(t1, t_min), np.full_like(t1, t_max))):
        live = hi > lo
        if not live.any():
            continue
        ts = lo[live, None] + (hi - lo)[live, None] * u[None, :]
        f = np.asarray(scene.value(o[live, None, :] + ts[:, :, None] * d[live, None, :]), np.float64)
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
    tangency could not be resolved, and t = NaN with an infinite bound on *every* ray once the
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
    rows = np.array([k for k in range(n) if brackets[k]], dtype=int)
    if rows.size:
        first = [min(brackets[k]) for k in rows]
        lo, hi = _bisect(scene, o, d, rows, np.array([b[0] for b in first]), np.array([b[1] for b in first]),
                         np.array([b[2] for b in first]))
        mid = lo + (hi - lo) / 2
        t[rows] = mid
        # the depth bound: the bracket widened by φ's rounding over the slope (reference.depthbound);
        # a bracket the rounding could explain away (no certified real crossing: a near-tangent
        # ray) is flagged, NaN.  Without a Lipschitz bound L = 1 scales the rounding model.
        w_lo, w_hi, crossing, _ = _depthbound.enclose(scene, o[rows], d[rows], lo, hi, 1.0 if L is None else L)
        err[rows] = np.where(crossing, np.maximum(mid - (lo - w_lo), (hi + w_hi) - mid), np.nan)
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
    width; the same certification as :func:`first_hit_numeric` (and its passes of :data:`CHUNK_RAYS` rays)."""
    o, d = _check(scene, o, d, t_min, t_max, n_samples)
    if o.shape[0] > CHUNK_RAYS:
        out, err = _by_chunks(lambda oc, dc: crossings_numeric(scene, oc, dc, t_min, t_max, lipschitz=lipschitz,
                                                               n_samples=n_samples), o, d)
        return out, (np.full_like(err, np.inf) if np.any(err == np.inf) else err)  # (one chunk refuted L)
    L = scene.info.lipschitz if lipschitz == "scene" else lipschitz
    t0, t1 = _search_range(scene, o, d, t_min, t_max, L)
    brackets, _, violated = _scan(scene, o, d, t0, t1, int(n_samples), L, 1e-12 * max(1.0, abs(t_max)), True)
    rows = np.array([k for k in range(o.shape[0]) for _ in brackets[k]], dtype=int)
    flat = [b for k in range(o.shape[0]) for b in brackets[k]]
    out = [np.zeros(0) for _ in range(o.shape[0])]
    err = np.zeros(o.shape[0])
    if flat:
        lo, hi = _bisect(scene, o, d, rows, np.array([b[0] for b in flat]), np.array([b[1] for b in flat]),
                         np.array([b[2] for b in flat]))
        mid = lo + (hi - lo) / 2
        for k in range(o.shape[0]):
            sel = rows == k
            out[k] = np.sort(mid[sel])
            if sel.any():
                err[k] = np.max(hi[sel] - lo[sel])
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
        if lipschitz is not None and not (math.isfinite(float(lipschitz)) and float(lipschitz) > 0):
            raise ValueError(f"lipschitz must be a finite number > 0 or None, got {lipschitz!r}")
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
        try:
            out = self.fn(x, xp) if self.params is None else self.fn(x, xp, cursor.take(self.params.copy()))
        except FieldError:
            raise
        except (Exception, SystemExit) as exc:  # (a field's sys.exit() is its failure, not the caller's exit)
            call = "fn(x, xp)" if self.params is None else "fn(x, xp, theta)"
            raise FieldError(f"{field_label(self)} raised {type(exc).__name__}: {exc} (evaluating {call} at "
                             f"points x of shape {tuple(getattr(x, 'shape', ()))}, {type(x).__module__.split('.')[0]} "
                             f"arrays; compute with the namespace xp it is given)") from exc
        return check_field_output(self, x, out, xp)

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
