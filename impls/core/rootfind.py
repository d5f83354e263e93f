"""Ray root finders as per-ray state machines: one φ evaluation per iteration per ray.

Each algorithm is ``start(xp, o, d) -> (t, hi, status)`` (the search intervals, and the rays
that finish before any evaluation), ``init(xp, o, d, ev, start=None) -> state`` and one step
function per *stage* (``alg.stages``, names of methods ``step(xp, state, o, d, ev) -> state``)
on a dict of per-ray arrays (leading dimension n), written with elementwise array-API operations
only, in the style of scipy's elementwise iterative methods
(``scipy/_lib/_elementwise_iterative_method.py``).
``state["phase"]`` is the index of the stage a ray is in; a stage hands a ray on by raising its
phase (to any later stage: a marching step that crosses skips the ladder stage).  Splitting an
algorithm into stages keeps each step lean (a marching step does not also compute the secant
update).  A backend's *loop driver* runs stage k while any ray has
status IN_PROGRESS and phase k: numpy and torch pass only those rays (compaction,
:mod:`impls.core.driver`), jax passes all rays of a chunk and keeps the old values of the others
(masking).  Both give identical per-ray results.

Ray: x(t) = o + t d with |d| = 1, search interval [t_min, t_max].  φ is evaluated through the
backend's ``ev(o, d, t, deriv) -> (f, df, cost)`` where ``df = dφ/dt = ⟨∇φ, d⟩`` (only when
``deriv``) and ``cost`` is the number of φ evaluations per ray it used (``evals``).

Per-ray outputs: ``t`` (depth; ``inf`` for MISS, NaN for NON_FINITE, the last iterate for
MAX_ITER, ``inf`` or the unresolved depth for UNCERTIFIED), ``status``
(:class:`impls.protocol.Status`), ``iterations`` and ``evals``.  What each method certifies and
can miss: docs/methods.md, "What each root finder can miss".
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from reference import raybounds

from ..protocol import Status

IN, CONV, MISS, MAXI, NONF, BAD, LIPV, UNC = (int(s) for s in (
    Status.IN_PROGRESS, Status.CONVERGED, Status.MISS, Status.MAX_ITER, Status.NON_FINITE, Status.BAD_INPUT,
    Status.LIPSCHITZ_VIOLATED, Status.UNCERTIFIED))


def bad_rays(xp, o, d):
    """Rays with a non-finite origin or direction (BAD_INPUT)."""
    return ~(xp.all(xp.isfinite(o), axis=1) & xp.all(xp.isfinite(d), axis=1))


def clip_to_bounds(xp, o, d, t_min: float, t_max: float, scene):
    """Per-ray search interval [lo, hi] = [t_min, t_max] ∩ ``scene.ray_bounds`` and the rays
    for which it is empty (``outside``); ``scene`` None: no clipping.

    :meth:`reference.scene.Field.ray_bounds` contains every t where φ(o + t d) ≤ 0 (a ball's
    chord, a box's slab test, a union's hull of its children's bounds, …, padded against
    rounding), so no crossing lies outside [lo, hi]."""
    if scene is None:
        return xp.full_like(o[:, 0], t_min), xp.full_like(o[:, 0], t_max), xp.zeros_like(o[:, 0], dtype=xp.bool)
    with raybounds.scene_rays(xp, o):  # float32: the pads cover the rays' own rounding
        lo, hi = scene.ray_bounds(xp, o, d)
    lo, hi = xp.maximum(lo, t_min), xp.minimum(hi, t_max)
    return lo, hi, ~(lo <= hi)


def _quiet(xp):
    """Silence numpy's divide warnings where a non-finite result is handled explicitly."""
    import contextlib

    import numpy as np

    return np.errstate(divide="ignore", invalid="ignore") if xp is np else contextlib.nullcontext()


def _device(a):
    """The device of array ``a`` (array_api_compat's, for every backend)."""
    import array_api_compat

    return array_api_compat.device(a)


def _repeat_rays(xp, a, k: int):
    """Rows of the (m, 3) ``a``, each repeated ``k`` times in a row: (m·k, 3), as the transposed
    view of a contiguous (3, m·k) array (the drivers' structure-of-arrays layout, in which
    numpy's φ runs on contiguous rows: :mod:`impls.core.driver`)."""
    m, c = a.shape
    return xp.permute_dims(xp.reshape(xp.broadcast_to(xp.permute_dims(a, (1, 0))[:, :, None], (c, m, k)), (c, m * k)),
                           (1, 0))


def _typed(xp, new: dict, old: dict) -> dict:
    """``new`` with the dtypes of ``old`` (python scalars in ``where`` may promote, e.g. to int64
    in torch; loop carries and scatter targets need fixed dtypes).  Entries already of that dtype
    are passed through without a call (a step's 15 calls are a measurable part of a few-ray step),
    and so are entries ``old`` lacks (a compacting driver carries only what a step reads; the
    steps make ``status`` and ``phase`` int32 themselves)."""
    return {k: v if k not in old or v.dtype == old[k].dtype else xp.astype(v, old[k].dtype) for k, v in new.items()}


def _init_status(xp, status, f, conv, unres=None):
    """Status after ``init``'s evaluation: of the rays IN_PROGRESS, NON_FINITE where φ is not
    finite, else CONVERGED where ``conv``, else UNCERTIFIED where ``unres`` (the start is within
    φ's rounding of the surface: which side it is on is not known); the others (BAD_INPUT, MISS)
    keep theirs."""
    live = status == IN
    out = xp.where(live & conv, CONV, status)
    if unres is not None:
        out = xp.where(live & ~conv & unres, UNC, out)
    return xp.where(live & ~xp.isfinite(f), NONF, out)


#: rays at or below which :func:`_verdict` picks the status with a chain of selects (fewer
#: operations: on few rays the per-call overhead is the cost) rather than a sum of indicators
#: (cheaper per element on many rays); the crossover lies between 4,096 and 65,536 rays on numpy
#: and torch (measurements: CHANGELOG.md, the entry on ``VERDICT_SELECT_RAYS``)
VERDICT_SELECT_RAYS = 4096


def _verdict(xp, nonf, conv, maxed, miss=None, lipv=None, unc=None):
    """Status of a stepped ray that was IN_PROGRESS: NON_FINITE (``nonf``), LIPSCHITZ_VIOLATED
    (``lipv``), UNCERTIFIED (``unc``), MISS (``miss``), CONVERGED (``conv``), MAX_ITER
    (``maxed``), in this order of precedence, else IN_PROGRESS.

    On many rays computed as IN + Σ (code − IN)·[indicator] over indicators made exclusive, not as
    nested selects: numpy's int32 ``where`` costs 2–8× an int32 add (4 nested ones were 2.6 of the
    15 ns per ray of a torus ∪ box march step besides φ).  On at most :data:`VERDICT_SELECT_RAYS`
    rays (a batch of stragglers), as selects from the lowest precedence up: 6 operations
    instead of ~30, the same integers."""
    i32 = xp.int32
    if nonf.shape[0] <= VERDICT_SELECT_RAYS:
        status = xp.astype(maxed, i32) * (MAXI - IN) + IN
        status = xp.where(conv, CONV, status)
        for flag, code in ((miss, MISS), (unc, UNC), (lipv, LIPV)):
            if flag is not None:
                status = xp.where(flag, code, status)
        return xp.where(nonf, NONF, status)
    ok = ~nonf
    if lipv is not None:
        lipv = lipv & ok
        ok = ok & ~lipv
    if unc is not None:
        unc = unc & ok
        ok = ok & ~unc
    if miss is not None:
        miss = miss & ok
        ok = ok & ~miss
    conv = conv & ok
    maxi = maxed & ok & ~conv
    status = xp.astype(conv, i32) * (CONV - IN) + xp.astype(maxi, i32) * (MAXI - IN) + xp.astype(nonf, i32) * (NONF - IN)
    if miss is not None:
        status = status + xp.astype(miss, i32) * (MISS - IN)
    if lipv is not None:
        status = status + xp.astype(lipv, i32) * (LIPV - IN)
    if unc is not None:
        status = status + xp.astype(unc, i32) * (UNC - IN)
    return status + IN


def lipschitz_violated(xp, f0, f1, t0, t1, inv_lip, mag, gain: float = 1.0):
    """Rays whose step from (t0, f0) to (t1, f1) shows |f1 − f0| > L·|t1 − t0|: the declared
    Lipschitz bound L = 1/``inv_lip`` is false on that ray, so no step computed from it is safe.

    Rounding slack, in depth units: |f1 − f0|/L may exceed |t1 − t0| by
    16ε·((|f0| + |f1|)/L + |t0| + |t1| + ``mag``), ε the dtype's, ``mag`` = |o|₁ + ``scale``
    (:func:`_magnitude`).  Why each term: the
    point x = o + t d is rounded by up to ε|x| per coordinate, |x| ≤ |o|₁ + |t|, which moves φ
    by up to L·ε|x|; φ's own evaluation rounds its intermediates, which for the fields here
    (distances to centres and planes, CSG min/max, affine layers) are bounded by |φ|/L, |x| and
    the scene's extent and offset ``scale`` (|centre| + radius of its bounding ball, see
    :func:`impls.core.methods_root.rounding_scale`); 16 covers the few operations of each.
    Without the |o| and ``scale`` terms an exact SDF far from the origin (a sphere of radius 1e6
    centred 1e6 away, seen from 3 units) is flagged: its φ carries ε·1e6 of rounding while
    |φ|, |t| ≈ 3.  The slack is a relative 1e-14 of those magnitudes, so an understated L is
    still seen on any step longer than that.  A NaN anywhere compares false (left to
    NON_FINITE).  ``gain`` (≥ 1) multiplies the slack for fields whose φ rounds worse than
    that (:func:`impls.core.methods_root.rounding_gain`: a mesh with skinny faces)."""
    eps = 16.0 * gain * _eps(t0)
    a0, a1 = xp.abs(f0), xp.abs(f1)
    at = xp.abs(t0) + xp.abs(t1) + mag
    if inv_lip != 1.0:
        return xp.abs(f1 - f0) * inv_lip > xp.abs(t1 - t0) + eps * ((a0 + a1) * inv_lip + at)
    return xp.abs(f1 - f0) > xp.abs(t1 - t0) + eps * (a0 + a1 + at)


def mid_probe(xp, alg, o, d, ev, t0, f0, t1, f1, inv_lip, mag):
    """(rays whose declared Lipschitz bound L = 1/``inv_lip`` is false inside the step from
    (t0, f0) to (t1, f1), evaluations per ray): φ evaluated once more at the step's midpoint, and
    the slope checked on both halves (:func:`lipschitz_violated`).

    The certified root finders run it on every marching step where the scene's bound is a
    declaration taken on trust (``alg.check_inside``, :func:`impls.core.methods_root.checks_inside`).
    A step's two ends alone cannot show an understated L where φ recovers past what the step
    jumped: from a start far from a field k× steeper than declared, the first step claims the
    whole ray empty, and both of its ends are consistent with L.  Along a ray meeting a surface at
    angle θ to its normal, a step of an understated bound overshoots only where the slope along the
    ray, k·cos θ, exceeds L, and the midpoint sees that slope on its way (a crossing inside a
    certified sphere is a slope above L, too).  A slope hidden between the three samples (a thin
    spike of φ) is left unseen (docs/methods.md, "What each root finder can miss").  It costs one
    evaluation per step on those scenes only."""
    t_m = t0 + 0.5 * (t1 - t0)
    t_m = xp.where(xp.isfinite(t_m), t_m, t0)
    f_m, _, cost = ev(o, d, t_m, False)
    return (lipschitz_violated(xp, f0, f_m, t0, t_m, inv_lip, mag, alg.gain)
            | lipschitz_violated(xp, f_m, f1, t_m, t1, inv_lip, mag, alg.gain)), cost


def _magnitude(xp, o, scale: float):
    """|o|₁ + ``scale`` per ray: the magnitude of the points φ is evaluated at beyond |t|, for the
    rounding slack of :func:`lipschitz_violated`."""
    return xp.abs(o[:, 0]) + xp.abs(o[:, 1]) + xp.abs(o[:, 2]) + scale


#: (ε, smallest normal) of each floating dtype asked for, by the backend's dtype object: the steps
#: ask on every iteration, and np.finfo by name costs microseconds a call (a few hundred rays'
#: torch step is ~100 µs all told)
_FINFO: dict = {}


def _finfo(a) -> tuple[float, float]:
    """(ε, smallest normal) of array ``a``'s floating dtype (any backend's: numpy's, torch's, …)."""
    got = _FINFO.get(a.dtype)
    if got is None:
        fi = np.finfo(np.dtype(str(a.dtype).rpartition(".")[2]))
        got = _FINFO[a.dtype] = (float(fi.eps), float(fi.tiny))
    return got


def _eps(a) -> float:
    """Machine epsilon of array ``a``'s floating dtype (any backend's)."""
    return _finfo(a)[0]


def resolution(xp, t, mag, gain: float = 1.0):
    """φ's rounding at depth ``t``, in depth units: 8·``gain``·ε·(|t| + ``mag``) (``mag`` =
    :func:`_magnitude`).  The point o + t·d is rounded by up to 2ε(|o|₁ + |t|), which moves a
    distance bound by up to L times that; φ's own operations (distances to centres and planes,
    CSG min/max, a rigid transform) add a few ε of |x| and the scene's extent: 8 covers both
    (:func:`lipschitz_violated` allows twice that, so that no exact SDF is ever flagged).  Where
    |φ|/L is no larger, the sign of the computed φ says nothing about the side of the surface
    the point is on: such a point is *unresolved*."""
    return (8.0 * gain * _eps(t)) * (xp.abs(t) + mag)


def unresolved(xp, f, t, inv_lip: float, mag, gain: float = 1.0):
    """Points where |φ|/L is at most φ's rounding (:func:`resolution`), φ = 0 included: their
    sign proves nothing and their certified radius (:func:`certified_radius`) is 0, so a march
    takes neither a side, a crossing nor a step from them.  (A
    computed φ = 0 is no root either: a ray lying in a face plane to rounding has φ = 0 all
    along it.  Inside a bracket whose ends are resolved, refinement still stops at φ = 0.)"""
    return xp.abs(f) * inv_lip <= resolution(xp, t, mag, gain)


def certified_radius(xp, f, t, inv_lip: float, mag, gain: float = 1.0):
    """The radius of the unbounding sphere at a point: |φ|/L less φ's rounding there
    (:func:`resolution`), at least 0.  No surface lies closer to the point than this, whatever
    φ's rounding (an unresolved point certifies nothing)."""
    return xp.maximum(xp.abs(f) * inv_lip - resolution(xp, t, mag, gain), 0.0)


def radius_and_unresolved(xp, f, t, inv_lip: float, mag, gain: float = 1.0):
    """(:func:`certified_radius`, :func:`unresolved`) of the same points, φ's rounding computed once
    (the same operations, so the same values as the two calls)."""
    q, res = xp.abs(f) * inv_lip, resolution(xp, t, mag, gain)
    return xp.maximum(q - res, 0.0), q <= res


def final_t(xp, t, status):
    """Depth as reported: ``inf`` for MISS, NaN for NON_FINITE, BAD_INPUT and
    LIPSCHITZ_VIOLATED (no depth was found), ``t`` otherwise (UNCERTIFIED: the step set it to
    ``inf`` or to the unresolved depth).  The steps
    leave a finished ray's ``t`` at its last point and the drivers map only the rays that
    finish (:func:`outputs`; the compacting driver on each step's leaving rows), which saves two
    full-size selects per step."""
    return xp.where(status == MISS, math.inf, xp.where((status == NONF) | (status == BAD) | (status == LIPV), math.nan, t))


def _outside_start(xp, alg, f, t, mag, inv_lip):
    """(φ at the start, unresolved starts) of a certified search.  A start the scene's ray bounds
    moved past ``t_min`` lies outside the solid by the bounds' own guarantee (they contain every
    point where φ ≤ 0, padded against rounding): there an unresolved φ is taken as on the outside
    (|φ|), and the start is not flagged; elsewhere an unresolved start is (UNCERTIFIED)."""
    unres = unresolved(xp, f, t, inv_lip, mag, alg.rg)
    if alg.bounds is None:
        return f, unres
    clipped = t > alg.t_min
    tiny = _finfo(f)[1]  # (φ = 0 there: the outside's sign)
    return xp.where(clipped & unres, xp.maximum(xp.abs(f), tiny), f), unres & ~clipped


class _Search:
    """What both root finders start from: their fields ``t_min``, ``t_max`` and ``bounds``."""

    @property
    def rg(self) -> float:
        """The gain on :func:`resolution` for this search's field: its rounding ``gain`` where φ is
        a distance bound (``resolve``: near the surface |∇φ| ≈ L, so the point's rounding moves φ
        by up to L times it), else 0: for a field flat at its roots (|x|³, an MLP whose bound L
        far exceeds its slope) |φ|/L says nothing of the distance, and only φ = 0 exactly is
        unresolved.  (Modelling the point's rounding there, L times it, was tried on 2026-11-30:
        sound, but with L up to 15,234 times the slope at the surface it left float32 almost no
        certified hit on such fields and none at a triple root; docs/methods.md, "Known limits".)"""
        return self.gain if self.resolve else 0.0

    def start(self, xp, o, d):
        """``(t, hi, status)`` of every ray before any evaluation (:func:`_start`)."""
        return _start(xp, o, d, self.t_min, self.t_max, self.bounds)


def _start(xp, o, d, t_min, t_max, bounds):
    """Start depth, per-ray end ``hi`` and initial status of every ray: BAD_INPUT, MISS (the
    search interval clipped to the scene's ray bounds is empty; its start depth is t_min, so
    that a masked driver evaluates φ at a finite point) or IN_PROGRESS.  Rays that finish here
    cost no evaluation: ``init`` counts one only for the rays still IN_PROGRESS (the compacting
    drivers drop the others before φ is evaluated, :mod:`impls.core.driver`)."""
    lo, hi, outside = clip_to_bounds(xp, o, d, t_min, t_max, bounds)
    status = xp.where(bad_rays(xp, o, d), BAD, xp.where(outside, MISS, IN))
    return xp.where(outside, t_min, lo), hi, xp.astype(status, xp.int32)


# -- sphere tracing ----------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class SphereTrace(_Search):
    """Sphere tracing (Hart 1996; lecture 'Sphere Tracing') with optional over-relaxation.

    Step t ← t + ω|φ(x(t))|/L, L the scene's Lipschitz bound (``|φ|`` so a ray starting inside
    marches to its exit).  With ω > 1 (Keinert et al., "Enhanced Sphere Tracing", STAG 2014):
    if the unbounding spheres of two consecutive points do not overlap (r_k + r_{k−1} < t_k −
    t_{k−1}, r = |φ|/L) the relaxed step may have jumped over the surface, so the tracer goes
    back to the safe point t_{k−1} + r_{k−1} and continues with ω = 1; a point is accepted only
    when that test passes, so over-relaxation never tunnels.  Radii are certified ones
    (:func:`certified_radius`: |φ|/L less φ's rounding).  Near the surface (the radius within
    δ₀ = max(tol/L, 4·rounding)) a step is a *probe* reaching δ past the sphere (δ = δ₀, doubled
    each time a probe lands where φ is unresolved).  CONVERGED on a resolved sign change against
    the ray's starting side whose bracket [t + r, t' − r'] is at most δ₀ wide, the depth the
    chord's zero in it; a probe's wider bracket (after retries, or under a mesh's rounding gain)
    is refined, keeping the first crossing, in the stage ``step_refine`` (:meth:`step_refine`),
    and is CONVERGED only once it is at most δ₀ wide, else UNCERTIFIED with its depth (the dtype
    cannot resolve the depth to tol: along a ray at slope s, φ's sign is rounding over a stretch
    about 2·rounding/s long).  MISS when the next t exceeds t_max
    (or leaves the scene's ray bounds, see :func:`clip_to_bounds`), if no probe stood without a
    sign change on the way (each leaves up to its reach uncovered) and φ is resolved where the last
    step ends (φ = 0 at t_max is a surface through the range's end), else UNCERTIFIED; a crossing
    found after a probe that left more than max(tol/L, 2ε|t|) uncovered is UNCERTIFIED too (with
    its depth: it is not proved the first where a pair could hide in that stretch); MAX_ITER
    after ``max_steps`` steps; LIPSCHITZ_VIOLATED when a step's ends differ by more than L
    times its length (the declared bound is false on that ray: :func:`lipschitz_violated`).
    One φ evaluation at t_min (the start of the ray bounds, when that is later) plus one per
    step; a step that leaves the range is evaluated where it ends, within t_max (``probe``: the
    scene's bound holds everywhere), else at the end of the ray bounds, so that its slope is
    checked too (a step over thin surface under a false L shows it).
    """

    inv_lip: float
    tol: float
    max_steps: int
    omega: float
    t_min: float
    t_max: float
    bounds: Any = None  # the scene whose ray_bounds clip the search (None: all of [t_min, t_max])
    probe: bool = False  # evaluate leaving steps where they end, within t_max (the scene's L holds there)
    scale: float = 0.0  # the scene's offset and extent, for the check's rounding slack (lipschitz_violated)
    gain: float = 1.0  # the scene's rounding gain, on that slack (lipschitz_violated)
    resolve: bool = False  # φ is a distance bound: its rounding near the surface is L·(point's rounding) (resolution)
    check_inside: bool = False  # L is a declaration taken on trust: check it inside every step (mid_probe)

    stages = ("step", "step_refine")

    #: a probe that lands within φ's rounding of 0 is repeated with twice the reach, at most this
    #: many times (then the ray is UNCERTIFIED: the dtype cannot resolve where it crosses)
    PROBE_RETRIES = 20

    #: what each stage's step reads, all that a compacting driver carries for it
    #: (:mod:`impls.core.driver`; ``status`` and ``phase`` are written afresh by every step)
    READS = {"step": frozenset({"t", "f", "pos", "unc", "wide", "t_prev", "f_prev", "r_prev", "mag", "pm", "omega",
                                "hi", "iterations", "evals"}),
             "step_refine": frozenset({"t", "f", "pos", "t_prev", "f_prev", "a", "b", "lo", "mag", "iterations",
                                       "evals"})}

    def reads(self, stage: str) -> frozenset[str]:
        """The state entries the step of ``stage`` reads (:data:`READS`)."""
        return self.READS[stage]

    def init(self, xp, o, d, ev, start=None):
        t, hi, status = self.start(xp, o, d) if start is None else start
        f, _, cost = ev(o, d, t, False)
        mag = _magnitude(xp, o, self.scale)
        f, unres = _outside_start(xp, self, f, t, mag, self.inv_lip)
        # (mag and the previous point's certified radius r_prev ride in the state: each step would
        # otherwise recompute them, ~15 of its ~100 array operations, the same values)
        s = {"t": t, "f": f, "pos": f > 0, "unc": xp.zeros_like(f, dtype=xp.bool),
             "wide": xp.zeros_like(f, dtype=xp.bool), "t_prev": t, "f_prev": f,
             "r_prev": certified_radius(xp, f, t, self.inv_lip, mag, self.rg), "mag": mag,
             "pm": xp.ones_like(t), "omega": xp.full_like(t, self.omega), "hi": hi, "a": t, "b": t, "lo": t,
             "status": status, "iterations": xp.zeros_like(o[:, 0], dtype=xp.int32),
             "evals": xp.astype(status == IN, xp.int32) * cost, "phase": xp.zeros_like(o[:, 0], dtype=xp.int32)}
        s["status"] = _init_status(xp, status, f, xp.zeros_like(unres), unres)
        return s

    def step(self, xp, s, o, d, ev):
        """One step of the tracer (the stage ``step``): its point (:meth:`_step_point`), φ there,
        and what follows from it (:meth:`_step_update`)."""
        p = self._step_point(xp, s)
        f_new, _, cost = ev(o, d, p["t_eval"], False)
        return self._step_update(xp, s, o, d, ev, p, f_new, cost)

    def _step_point(self, xp, s) -> dict:
        """Where a step evaluates φ (``t_eval``), and the quantities its update reads."""
        t, f, om, hi, mag = s["t"], s["f"], s["omega"], s["hi"], s["mag"]
        r = certified_radius(xp, f, t, self.inv_lip, mag, self.rg)
        r_prev = s["r_prev"]  # certified_radius of (f_prev, t_prev): the last step's base radius rb
        # Keinert's fallback: the last relaxed step's spheres did not overlap, so the tracer steps
        # again from the point before it, with ω = 1
        fail = (om > 1) & (r + r_prev < t - s["t_prev"])
        tb = xp.where(fail, s["t_prev"], t)  # the step's base: an accepted point, its sphere certified
        fb = xp.where(fail, s["f_prev"], f)
        rb = xp.where(fail, r_prev, r)
        om = xp.where(fail, xp.ones_like(om), om)
        # near the surface (|φ| ≤ tol, or within a few roundings of 0) the step is a probe: it reaches
        # past the base's sphere by δ, so that a crossing there shows as a sign change within δ.  δ is
        # at least 2ε|t|, two spacings of the floats at t: a shorter step leaves t where it is
        # (t + r rounds to t), and a field whose rounding is not modelled (rg = 0: not a distance
        # bound, e.g. an MLP) with tol/L below the spacing would stall there until max_steps
        spacing = (2.0 * _eps(t)) * xp.abs(tb)
        d0 = xp.maximum(xp.maximum(4.0 * resolution(xp, tb, mag, self.rg), self.tol * self.inv_lip), spacing)
        near = rb <= d0
        reach = s["pm"] * d0
        # a relaxed step that would leave the range where a plain one does not is taken plain: the
        # range's end must be covered by a certified sphere for a MISS
        plain = near | ((tb + om * rb > hi) & (tb + rb <= hi))
        t_new = tb + xp.where(near, rb + reach, xp.where(plain, rb, om * rb))
        # beyond hi, or past every finite depth (t_max = inf and no ray bound): the ray left
        out = (t_new > hi) | ~xp.isfinite(t_new)
        # a leaving ray is evaluated where its step ends (within t_max; past the ray bound φ is still
        # defined, and where the scene's L holds everywhere also still bounded by L), so that a step
        # which jumped over thin surface under a false L shows its slope; else at the bound's end
        t_far = xp.minimum(t_new, self.t_max if self.probe else hi)
        t_eval = xp.where(out, xp.where(xp.isfinite(t_far), t_far, tb), t_new)
        return dict(t_eval=t_eval, tb=tb, fb=fb, rb=rb, om=om, near=near, spacing=spacing, t_new=t_new, out=out)

    def _step_update(self, xp, s, o, d, ev, p, f_new, cost):
        """The step's new state from φ at its point (``f_new``, ``cost`` evaluations per ray)."""
        t, f, hi, mag = s["t"], s["f"], s["hi"], s["mag"]
        t_eval, tb, fb, rb, om, near, spacing, t_new, out = (
            p[k] for k in ("t_eval", "tb", "fb", "rb", "om", "near", "spacing", "t_new", "out"))
        iters = s["iterations"] + 1
        fin = xp.isfinite(f_new)
        # φ = +inf on a search with no end: the point left the range where φ is representable, which
        # is empty space; the ray has left every finite depth (a MISS, not NON_FINITE)
        beyond = (f_new == math.inf) & (hi == math.inf)
        out = out | beyond
        r_new, unres = radius_and_unresolved(xp, f_new, t_eval, self.inv_lip, mag, self.rg)
        # a resolved sign change within the range, against the side the ray is on (a crossing past
        # hi, where the ray bound says there is no surface, is not one)
        cross = fin & ~unres & (t_eval <= hi) & ((f_new > 0) != s["pos"])
        # every crossing lies in [tb + rb, t_eval − r_new]: converged when that is at most tol/L wide
        # (a plain step's is empty, up to the rounding of the sum); a probe whose reach φ's rounding
        # made wider than that brackets the crossing only to the dtype's resolution: UNCERTIFIED
        gap = (t_eval - tb) - rb - r_new
        slack = (4.0 * _eps(t)) * xp.abs(t_eval)
        # (the generic rounding model, without a mesh's gain: a depth known to a few of those is
        # what the dtype resolves; a probe repeated across an unresolved stretch widens it)
        res0 = 4.0 * resolution(xp, tb, mag, 1.0 if self.resolve else 0.0)
        base = xp.maximum(xp.maximum(self.tol * self.inv_lip, res0), spacing)
        allow = s["pm"] * base + slack
        conv = cross & (gap <= base + slack) & ~s["wide"]
        # a probe's bracket wider than δ (its reach doubled by retries, or φ's rounding gain on a
        # mesh) is shrunk from its far end in the next stage (step_refine); after a wide stand the
        # crossing is not proved the first, however narrow its bracket
        refine = cross & ~conv & near & ~s["wide"]
        coarse = cross & ~conv & s["wide"]
        # a probe landing within φ's rounding says nothing: the ray stays and probes twice as far
        retry = near & unres & ~out
        give_up = retry & (s["pm"] >= 2.0 ** self.PROBE_RETRIES)
        # a probe that stands without a sign change leaves up to its reach uncovered: within the
        # allowance a MISS is then uncertified; past it (a probe whose reach φ's rounding widened) a
        # crossing pair may hide there, and the ray ends UNCERTIFIED
        stood = near & ~cross & ~unres & ~out & (gap > 0)
        unc = s["unc"] | stood
        # a probe that stood leaving more than tol/L uncovered (its reach widened by φ's rounding or by
        # retries: float32 far from the origin, where 4 roundings reach 0.08 at 1e4) may hide a crossing
        # pair the user's tolerance would see: a crossing found after it is not proved the first
        # (UNCERTIFIED, with its depth), as the hybrids' after a step that stood uncertified
        wide = s["wide"] | (stood & (gap > xp.maximum(self.tol * self.inv_lip, spacing) + slack))
        give_up = give_up | (stood & (gap > allow)) | coarse
        miss = out & ~cross
        covered = (tb + rb >= hi) | (t_eval - r_new <= tb + rb)
        # φ within rounding of 0 where the ray ends (φ = 0 exactly at t_max: a surface through the
        # range's end point) proves no side there: the spheres cover [t_min, t_max), not t_max itself
        unc_miss = miss & (unc | ~covered | unres)
        # the step's two ends are evaluated: a slope above L shows the declared bound is false
        lipv = lipschitz_violated(xp, f, f_new, t, t_eval, self.inv_lip, mag, self.gain) & ~beyond
        if self.check_inside:
            inside, extra = mid_probe(xp, self, o, d, ev, tb, fb, t_eval, f_new, self.inv_lip, mag)
            lipv, cost = lipv | (inside & ~beyond), cost + extra
        # (a ray that left has no depth to lose to a non-finite φ: it is a MISS, or flagged)
        stay = retry & ~give_up
        status = _verdict(xp, ~fin & ~out, conv, iters >= self.max_steps, miss=miss & ~unc_miss, lipv=lipv,
                          unc=unc_miss | give_up)
        # the depth: the zero of the chord from the base to t_eval, within the bracket
        with _quiet(xp):
            z = tb + (t_eval - tb) * (fb / (fb - f_new))
        # (never 0/0 where it is used: a crossing's f_new is resolved, so nonzero, and a ray in
        # progress has a finite base fb; step_refine's chord can have no zero)
        z = xp.minimum(xp.maximum(z, tb + rb), t_eval)
        t_out = xp.where(conv | coarse, z, xp.where(unc_miss, math.inf, xp.where(
            stay, t, xp.where(give_up | refine, t_eval, t_new))))
        # (a refining ray carries its bracket [tb + rb, t_eval − r_new] and, as t and f, its far sample)
        a = tb + rb
        return _typed(xp, dict(s, t=t_out, f=xp.where(stay, f, f_new), t_prev=tb, f_prev=fb, r_prev=rb, omega=om,
                               pm=xp.where(retry, 2.0 * s["pm"], s["pm"]), status=status, unc=unc, wide=wide,
                               a=a, b=t_eval - r_new, lo=a, phase=xp.astype(refine, xp.int32),
                               iterations=iters, evals=s["evals"] + cost), s)

    def step_refine(self, xp, s, o, d, ev):
        """One refinement step of a probe's crossing bracketed wider than δ = max(tol/L,
        4·rounding) (its reach doubled by retries across a stretch where φ is unresolved, or a
        mesh's rounding gain).  The first crossing lies in [a, b]: certified spheres cover the ray
        up to ``a``, and a resolved sample of the other side, (``t``, ``f``), has its sphere beyond
        ``b``.  Steps alternate between two samples, one φ evaluation each:

        * the frontier ``a`` itself (even steps, and every step once the search below is spent), a
          sphere-tracing step: a resolved sample of the start's side moves ``a`` to a + r_a; an
          unresolved one leaves it (the frontier has reached the stretch where φ's sign is rounding);
        * c = lo + (b − lo)/2, a bisection from the far end: a resolved sample of the other side
          moves ``b`` to c − r_c; one of the start's side whose sphere reaches back to ``a`` moves
          ``a`` to c + r_c; any other (unresolved, or of the start's side beyond ``a``, where a
          pair of crossings may lie before it) moves only the search's left end ``lo`` to c.

        CONVERGED when b − a ≤ δ, the depth the zero of the chord from the step's base (tb, φ(tb))
        to (t, f), within [a, b] (its middle where the chord has no zero: t = tb, or φ = 0 at both
        ends); UNCERTIFIED with that depth when neither end can move on: the frontier stands at an
        unresolved sample or crawls (its sphere under 1/:data:`CERTIFY_REACH` of what is left
        beyond δ) and the stretch left to search, [lo, b], is under δ/4.  The first crossing then
        lies in a stretch where φ's sign is rounding, about 2·rounding/s long on a ray meeting the
        surface at slope s (in units of L), which the dtype resolves only to b − a.
        Each sample's slope from the base is checked (:func:`lipschitz_violated`).  Why this stage:
        a bracket left as its k-times retried probe found it is only 2^k·δ wide (docs/methods.md)."""
        p = self._refine_point(xp, s)
        f_c, _, cost = ev(o, d, p["c"], False)
        return self._refine_update(xp, s, p, f_c, cost)

    #: the one stage a masked driver (jax's, :mod:`impls.jax.driver`) runs instead of ``stages``
    masked_stages = ("step_masked",)

    def step_masked(self, xp, s, o, d, ev):
        """Both stages in one step, for a masked driver, which steps every row of a batch on each
        iteration: a row in refinement (phase 1) evaluates the refinement's point, any other the
        tracer's, in one φ evaluation, and takes that stage's update.  The per-ray results are the
        staged drivers'; the point is one traced φ per loop instead of one per stage (a jax kernel's
        compile time is mostly its loops' φ)."""
        rf = s["phase"] == 1
        p1, p2 = self._step_point(xp, s), self._refine_point(xp, s)
        f_new, _, cost = ev(o, d, xp.where(rf, p2["c"], p1["t_eval"]), False)
        n1 = self._step_update(xp, s, o, d, ev, p1, f_new, cost)
        n2 = self._refine_update(xp, s, p2, f_new, cost)
        return {k: xp.where(rf, n2[k], n1[k]) for k in n1}

    def _refine_point(self, xp, s) -> dict:
        """Where a refinement step evaluates φ (``c``), and the quantities its update reads."""
        t, tb, a, b, lo, mag = s["t"], s["t_prev"], s["a"], s["b"], s["lo"], s["mag"]
        slack = (4.0 * _eps(t)) * xp.abs(t)
        spacing = (2.0 * _eps(tb)) * xp.abs(tb)
        res0 = 4.0 * resolution(xp, tb, mag, 1.0 if self.resolve else 0.0)
        base = xp.maximum(xp.maximum(self.tol * self.inv_lip, res0), spacing) + slack
        front = (s["iterations"] % 2 == 0) | (b - lo <= 0.25 * base)
        return dict(c=xp.where(front, a, lo + 0.5 * (b - lo)), front=front, base=base, slack=slack)

    def _refine_update(self, xp, s, p, f_c, cost):
        """The refinement step's new state from φ at its point (``f_c``, ``cost`` evaluations per ray)."""
        t, f, tb, fb, a, b, lo, mag = s["t"], s["f"], s["t_prev"], s["f_prev"], s["a"], s["b"], s["lo"], s["mag"]
        c, front, base, slack = p["c"], p["front"], p["base"], p["slack"]
        iters = s["iterations"] + 1
        fin = xp.isfinite(f_c)
        r_c, unres = radius_and_unresolved(xp, f_c, c, self.inv_lip, mag, self.rg)
        other = ~unres & ((f_c > 0) != s["pos"])
        if self.rg == 0.0:
            # where φ's rounding is not modelled (not a distance bound) only φ = 0 is unresolved, and
            # inside a bracket of resolved signs it is taken as the root, as the hybrids' refinement does
            other = other | (f_c == 0)
        # a resolved sample of the start's side whose sphere reaches back to the frontier moves it on
        # (the frontier's own sample always does); one of the other side bounds the crossing before
        # its sphere (at the frontier itself, where the spheres behind said no crossing, that is
        # rounding: the bracket closes there)
        reach = ~unres & ~other & (c - r_c <= a + slack)
        b_n = xp.where(other, xp.maximum(c - r_c, a), b)
        a_n = xp.minimum(xp.where(reach, xp.maximum(a, c + r_c), a), b_n)
        lo_n = xp.minimum(xp.maximum(xp.where(front | other, lo, c), a_n), b_n)
        t_n, f_n = xp.where(other, c, t), xp.where(other, f_c, f)
        conv = b_n - a_n <= base
        stuck = front & (~reach | (a_n <= a) | (r_c * CERTIFY_REACH < b_n - a_n - base))
        unc = ~conv & stuck & (b_n - lo_n <= 0.25 * base)
        lipv = lipschitz_violated(xp, fb, f_c, tb, c, self.inv_lip, mag, self.gain)
        status = _verdict(xp, ~fin, conv, iters >= self.max_steps, lipv=lipv, unc=unc)
        with _quiet(xp):
            z = tb + (t_n - tb) * (fb / (fb - f_n))
        # a chord without a zero (0/0: the base and the sample both φ = 0, as float32's rounding
        # gives; 0·inf: the sample at the base) leaves the bracket's middle, within δ of the
        # crossing wherever the ray converged
        z = xp.where(z == z, z, 0.5 * (a_n + b_n))
        z = xp.minimum(xp.maximum(z, a_n), b_n)
        return _typed(xp, dict(s, t=xp.where(conv | unc, z, t_n), f=f_n, a=a_n, b=b_n, lo=lo_n, status=status,
                               iterations=iters, evals=s["evals"] + cost), s)


# -- marching to a sign change, then refinement ------------------------------------------------
#
# A marching root finder is a record of three pieces: a step rule (how far a marching step goes
# and whether it stands), a refiner (how a bracket shrinks) and the ladder setting.  Each piece
# says which state entries it holds between steps (``holds``), so that the stages' reads are
# derived, not listed (:meth:`MarchRefine.reads`).


@dataclasses.dataclass(frozen=True)
class ConstantStep:
    """Constant marching step h = ``step`` (DVR, UNISURF).  A surface crossed twice within one
    step (a feature thinner than the step) is not seen by the samples — marching's limit; what
    the march reports is certified against it as follows.  Every step stands; where the scene
    declares a bound L (``check_inv_lip`` = 1/L), every step checks it (:func:`lipschitz_violated`).

    With ``cover`` (a bound L the scene declares and the library does not take on trust), a step
    that does not cross is *covered* when the unbounding spheres of its ends overlap,
    rc₀ + rc₁ ≥ h (:func:`certified_radius`: |φ|/L less φ's rounding), as the hybrid's steps are
    certified: no surface lies in it.  The *frontier* g (state ``g``) is where the covered stretch
    from the ray's start ends: t₀ + rc₀ of the first step that stood uncovered (inf while there
    is none; the start itself without ``cover``, where no sample proves anything).

    * MISS only with g = inf (every step covered), else UNCERTIFIED with depth inf.
    * A sign change to or from an *unresolved* sample (|φ|/L within φ's rounding, certified
      radius 0; without a bound, φ = 0 exactly) proves no crossing: UNCERTIFIED at that sample.
      A ray lying in a face plane to rounding has φ = 0 all along it (a touch, not a crossing).
    * CONVERGED only when g + h reaches the closed bracket's start a (its point, for φ = 0
      exactly), else UNCERTIFIED with the depth found: no crossing lies before g, so the first
      one lies in [g, b] and the depth is within h + ``xtol`` of it — the hybrid's guarantee
      with ``min_step`` = h (:meth:`MarchRefine._certify`).  Every step covered before the
      crossing step always meets it.  Approached at slope σ (in units of L), the step before a
      crossing is covered only while φ there is at least about h·(1 − σ)/2, so a shallow hit
      is often UNCERTIFIED: the march's samples did not prove it the first."""

    step: float
    check_inv_lip: float | None = None
    cover: bool = False

    #: constant steps rely on no bound to step: they stand uncertified, and no certification stage
    #: samples between them; the frontier ``g`` of the samples' spheres (``cover``) certifies
    #: what the march reports
    certifies = False

    @property
    def min_step(self) -> float:
        return self.step

    @property
    def check(self) -> float | None:
        """1/L of the bound the marching steps check (None: no check)."""
        return self.check_inv_lip

    def holds(self, stage: str) -> frozenset[str]:
        return frozenset({"g"})

    def init(self, xp, t) -> dict:
        # g: the frontier, where the stretch the samples' spheres covered from the start ends
        # (inf: no step stood uncovered; without cover, the start: nothing is covered)
        return {"g": xp.full_like(t, math.inf) if self.cover else t}

    def late(self, xp, g, lo):
        """Closed brackets starting at ``lo`` that the frontier ``g`` leaves more than a step
        behind: their crossing is not certified the first (UNCERTIFIED)."""
        return g + self.step < lo

    def covered(self, xp, rc, rc_n, h):
        """Steps of length ``h`` whose ends' certified radii ``rc``, ``rc_n`` overlap (free of
        surface), or that end past every finite depth."""
        return (rc + rc_n >= h) | ~xp.isfinite(h)

    def size(self, xp, s, t, f, rc=None):
        """(|φ|/L or None, the step h) of a marching step from (t, f)."""
        return None, self.step

    def end(self, xp, t, h, hi, t_max):
        """Where the step from t ends: t + h, clamped to the ray's end ``hi``."""
        return xp.minimum(t + h, hi)

    def judge(self, xp, s, cross, rc, rc_n, h, t_n):
        """(stands, new state entries, stood uncertified) of a step: a constant step always stands."""
        return None, {}, None

    def ladder_size(self, xp, s, t, f, rc=None):
        return None, xp.full_like(t, self.step)

    def ladder_certified(self, xp, Rp, R, T, Tp, hi, h):
        """(pairs that stand, pairs certified free of surface) of a ladder: None, None here."""
        return None, None

    def ladder_adapt(self, xp, s, stopped, cross_e, e0, k) -> dict:
        return {}


#: the hybrid's crossing step is taken once the stretch it would leave uncertified, x₀ − r, is
#: predicted within this many ``min_step`` (:meth:`CertifiedStep.size`); the over-relaxed step is
#: this fraction of the largest step the secant's slope certifies (a margin against a slope that
#: grows: 1 had 0.38 rejected steps per ray on bench speed's torus ∪ box, 0.9 has 0.06).  Measured
#: on that scene at 256² and 1024²: GATE 0.3, 0.5, 1, 3, 10 cost 6.72, 6.55, 5.95, 6.42, 7.20
#: evaluations per ray (docs/methods.md)
GATE = 1.0
OVER_RELAX = 0.9
#: below this slope (in units of L) a ray is taken to pass a surface nearly tangent rather than
#: approach it, and the forced step Δ keeps it moving (at 1/64 the MLP camera's hits, approached at
#: slopes about 0.03 of its loose bound, stood uncertified; at 1/1024 rays grazing a sphere within
#: 1e-6 crawl 269 evaluations per ray to the same UNCERTIFIED)
PASSING_SLOPE = 1.0 / 256.0


@dataclasses.dataclass(frozen=True)
class CertifiedStep:
    """The hybrid's step rule (:meth:`size`): over-relaxed certified steps, a crossing step once
    the stretch it leaves uncertified is under ``GATE`` · ``min_step`` (``extrapolate``, within
    ``reach``), and, on a ray passing a surface nearly tangent, a per-ray forced step Δ (state
    ``dl``) in [``min_step``, ``overstep``].  A step stands when certified free of surface by
    overlapping unbounding spheres (Keinert et al. 2014), when it crosses, or when it is no longer
    than ``min_step`` (uncertified: :class:`MarchRefine` records where, state ``g``); a leaving step
    is evaluated where it ends (``probe``, within t_max).  Every step checks the bound L =
    1/``inv_lip`` it relies on.  A rejected step is followed by the plain step r = |φ|/L; should
    that one be rejected too (φ's rounding alone: its end within rounding of a surface it does
    not cross, so rc + rc_n < r for the certified radii rc = r less rounding), the next is
    max(rc, ``min_step``), which stands whatever the rounding: certified when rc, uncertified when
    ``min_step`` (state ``dl`` = 0 marks it).  Before, the ray repeated the same rejected step to
    ``max_steps``: 124,344 of a 1024² float32 camera's rays on the fin mesh; stepping rc alone
    left 10 of them creeping along the wall by rc ≪ ``min_step``."""

    inv_lip: float
    min_step: float
    overstep: float  # largest forced step Δ beyond |φ|/L, ≥ min_step (overstep = min_step: the plain IDR march)
    extrapolate: float = 0.0  # forced step ≥ this × the secant's distance to the zero (0: off)
    reach: float = 0.0  # largest extrapolated step
    probe: bool = False  # evaluate leaving steps where they end, within t_max (L holds there)

    #: its steps are certified by the bound: a crossing is checked to be the first, a MISS certified
    certifies = True

    def __post_init__(self):
        if not self.overstep >= self.min_step:
            raise ValueError(f"CertifiedStep: overstep={self.overstep!r} must be ≥ min_step={self.min_step!r}")

    @property
    def check(self) -> float:
        return self.inv_lip

    @property
    def cap(self) -> float:
        """Largest forced step beyond |φ|/L."""
        return self.overstep

    def holds(self, stage: str) -> frozenset[str]:
        march = {"pl"} | ({"p", "fp"} if self.extrapolate else set())
        return frozenset({"dl", "g"} | (march if stage == "step_march" else set()))

    def radius(self, xp, f):
        """|φ|/L, the radius of the unbounding sphere (no multiplication for L = 1, an SDF's)."""
        return xp.abs(f) if self.inv_lip == 1.0 else xp.abs(f) * self.inv_lip

    def init(self, xp, t) -> dict:
        # g: where the first stretch no certified sphere covered begins (a step ≤ min_step that
        # stood uncertified; inf: none): a MISS is then uncertified, and a crossing is certified
        # only if it lies within min_step of g.  pl: the length of a probe past a landing within
        # φ's rounding of 0 (0: none pending; −1: the ray's one probe is spent)
        return {"dl": xp.full_like(t, self.cap), "g": xp.full_like(t, math.inf), "pl": xp.zeros_like(t)}

    def size(self, xp, s, t, f, rc=None):
        r = self.radius(xp, f)
        # a plain step r can be rejected by φ's rounding alone (its end within rounding of a
        # surface it does not cross: rc + rc_n < r); repeating it would repeat the rejection to
        # max_steps, so the ray steps its certified radius rc next, which stands whatever φ's
        # rounding, or min_step where rc is shorter (standing uncertified, as any step that short:
        # a ray that stepped rc < min_step crawled along a wall within φ's rounding to max_steps)
        # (state dl = 0 marks it: MarchRefine.step_march)
        r0 = r if rc is None else xp.where(s["dl"] < self.min_step, rc, r)
        h = xp.maximum(r0, xp.maximum(s["dl"], self.min_step))
        if self.extrapolate:
            # σ: the fall of |φ|/L per unit depth over the last step (≤ 1 by the bound), the slope at
            # which the ray approaches the surface (NaN after a rejection or at the start: p = t).
            # Over-relaxation (Keinert et al. 2014): where φ falls linearly at slope σ the spheres of
            # t and t + h overlap while h ≤ 2r/(1 + σ), so that step stands certified and leaves
            # (1 − σ)/(1 + σ) of the distance to the surface, against 1 − σ for the plain step r
            # (a receding ray, σ ≤ 0: 2r).  A step whose spheres do not overlap after all is rejected
            # (the ray stays, and steps r next).  Below the slope PASSING_SLOPE (a ray passing a
            # surface, nearly tangent) the forced step Δ keeps it moving.  The crossing step: the
            # secant through the last two points predicts the zero at x₀ = r/σ; the step e·x₀
            # (within reach) crosses and leaves uncertified the stretch from the sphere's end t + r
            # to the crossing, x₀ − r, which the certification stage must then cover (_certify),
            # so it is taken once that is within GATE·min_step.
            rs = r if rc is None else rc  # the spheres judge() overlaps: less φ's rounding
            with _quiet(xp):
                span = t - s["p"]
                sig = xp.minimum((self.radius(xp, s["fp"]) - r) / span, 1.0)
                # no slope without a last step (the start, a rejection: p = t) by definition, not by
                # 0/0: a compiler that contracts |φ_p|/L − |φ|/L into a fused multiply-add leaves
                # the product's rounding in the numerator (jax on the CPU: 4e-20/0 = inf, σ = 1, a
                # crossing step that is rejected and taken again until max_steps)
                sig = xp.where(span > 0, sig, xp.full_like(sig, math.nan))
                over = xp.where(sig > -1.0, r + OVER_RELAX * (2.0 * rs / (1.0 + xp.maximum(sig, 0.0)) - r), r0)
                x0 = r / sig
                x = xp.minimum(self.extrapolate * x0, self.reach)
                base = xp.where(sig > PASSING_SLOPE, over, xp.maximum(h, over))
                cross = (sig > 0) & (x0 - r <= GATE * self.min_step) & (x > base)
            h = xp.where(cross, x, base)
        return r, xp.maximum(h, s["pl"])

    def end(self, xp, t, h, hi, t_max):
        t_n = xp.minimum(t + h, hi)
        if self.probe:
            # a leaving step is evaluated where it ends (within t_max: φ is defined past the ray bound,
            # and bounded by L where the scene states no domain), so that its slope is checked too
            t_n = xp.where(t + h > hi, xp.minimum(t + h, t_max), t_n)
        return t_n

    def judge(self, xp, s, cross, rc, rc_n, h, t_n):
        # stands: certified by overlapping unbounding spheres (rc + rc_n ≥ h with the radii less
        # φ's rounding, which a safe step h = |φ|/L passes up to that rounding; h ≥ t_n − t, so a
        # step clamped at t_max is judged conservatively), a crossing (checked to be the first by
        # the refinement stage), or a step no longer than min_step, which stands uncertified.  A
        # rejected step stays where it was.  (A step past every finite depth needs no certificate:
        # nothing lies beyond it.)
        finite = xp.isfinite(t_n)
        sure = (rc + rc_n >= h) | ~finite
        ok = cross | sure | (h <= self.min_step)
        return ok, {"dl": xp.clip(xp.where(ok, 2 * s["dl"], 0.5 * s["dl"]), self.min_step, self.cap)}, ok & ~cross & ~sure

    def ladder_size(self, xp, s, t, f, rc=None):
        r = self.radius(xp, f)
        r0 = r if rc is None else xp.where(s["dl"] < self.min_step, rc, r)  # (as in size)
        return r, xp.maximum(r0, xp.maximum(s["dl"], self.min_step))

    def ladder_certified(self, xp, Rp, R, T, Tp, hi, h):
        # as a single step, judged on the requested spacing h, except pairs ending at hi, which
        # are shorter (the samples past hi all sit at hi: pairs of length 0); Rp, R the certified
        # radii at the pairs' ends
        spacing = xp.where(T >= hi[:, None], T - Tp, h[:, None])
        sure = Rp + R >= spacing
        return sure | (h <= self.min_step)[:, None], sure

    def ladder_adapt(self, xp, s, stopped, cross_e, e0, k) -> dict:
        grow = xp.where(~stopped, 2 * s["dl"], xp.where(~cross_e & (e0 < k // 2), 0.5 * s["dl"], s["dl"]))
        return {"dl": xp.clip(grow, self.min_step, self.cap)}


class Bisect:
    """Bisection of the bracket [a, b]: the midpoint (linear convergence, ratio 1/2)."""

    deriv = False

    def holds(self, stage: str) -> frozenset[str]:
        return frozenset()

    def propose(self, xp, s, t, f, a, b, mid, i2, xtol):
        return mid

    def report(self, xp, c, f_c, t, f, na, nb, conv):
        return c

    def on_bracket(self, xp, width) -> dict:
        return {}

    def after(self, xp, s, i2, a, b, df_c) -> dict:
        return {}


class _OneSided:
    """A refiner whose iterates close in from one side (secant, Newton), safeguarded."""

    deriv = False

    def holds(self, stage: str) -> frozenset[str]:
        return frozenset({"wq"} if stage == "step_refine" else set())

    def _iterate(self, xp, s, t, f):  # pragma: no cover - each refiner has its own
        raise NotImplementedError

    def propose(self, xp, s, t, f, a, b, mid, i2, xtol):
        with _quiet(xp):  # f = fp or φ' = 0 give inf/NaN: replaced by the midpoint below
            c = self._iterate(xp, s, t, f)
        # t is an end of the bracket.  Near a root secant and Newton close in from one side and the
        # far end stays put, so no bracket would ever certify them: a step shorter than h = xtol/2 is
        # lengthened by h/2 beyond the predicted root, whose evaluation then closes the bracket
        # to < xtol (Brent's "step at least tol" rule, scipy's Chandrupatla likewise).  h is at
        # least two float spacings of t: with xtol below the spacing, as 1e-12 is in float32, a
        # lift of xtol/4 rounds to t itself, the same point is evaluated again, and only the
        # safeguard's bisections every third step close the bracket, to adjacent floats
        h = xp.maximum(0.5 * xtol, (2.0 * _eps(t)) * xp.abs(t))
        step = xp.abs(c - t)
        lift = step + 0.5 * h  # (both branches arrays: a where on two Python floats would be float64)
        c = xp.where(step < h, xp.where(t - a <= b - t, t + lift, t - lift), c)
        # safeguards (rtsafe, Numerical Recipes §9.4; Brent): bisect where the iterate leaves the
        # closed bracket (or is NaN), and where the bracket did not halve over the last three steps
        # (checked every third iteration), so a multiple root or a poor derivative costs at most
        # three times bisection's steps (every second iteration forced bisections on healthy
        # one-sided Newton runs: sphere, 128² rays, 14.4 → 35.5 evaluations per ray; every third: 16.2)
        slow = i2 & (b - a > 0.5 * s["wq"])
        return xp.where((c >= a) & (c <= b) & ~slow, c, mid)

    def report(self, xp, c, f_c, t, f, na, nb, conv):
        # report the zero of the chord through the last two iterates, kept in the certified bracket:
        # after the lengthened step they are the bracket's ends, and it is far more accurate than c
        with _quiet(xp):
            z = c - f_c * (c - t) / (f_c - f)
        z = xp.minimum(xp.maximum(z, na), nb)
        return xp.where(conv & (f_c != 0) & (z == z), z, c)

    def on_bracket(self, xp, width) -> dict:
        return {"wq": 4.0 * width}  # refinement's "width at the last check": no forced bisection at first

    def after(self, xp, s, i2, a, b, df_c) -> dict:
        return {"wq": xp.where(i2, b - a, s["wq"])}


class Secant(_OneSided):
    """Secant on the last two iterates (order (1+√5)/2 near a simple root)."""

    def holds(self, stage: str) -> frozenset[str]:
        return super().holds(stage) | ({"p", "fp"} if stage == "step_refine" else frozenset())

    def _iterate(self, xp, s, t, f):
        return t - f * (t - s["p"]) / (f - s["fp"])


class Newton(_OneSided):
    """Newton t ← t − φ/φ' with φ' = ⟨∇φ, d⟩ (order 2); φ' is evaluated with φ at every point."""

    deriv = True

    def holds(self, stage: str) -> frozenset[str]:
        return super().holds(stage) | {"df"}

    def _iterate(self, xp, s, t, f):
        return t - f / s["df"]

    def after(self, xp, s, i2, a, b, df_c) -> dict:
        return {**super().after(xp, s, i2, a, b, df_c), "df": df_c}


REFINERS = {"bisect": Bisect, "secant": Secant, "newton": Newton}


@dataclasses.dataclass(frozen=True)
class MarchRefine(_Search):
    """March to the first sign change of φ along the ray (stage ``step_march``, then, for rays
    still marching after ``ladder_after`` steps, stage ``step_ladder``), then refine the bracket
    (stage ``step_refine``).

    Marching (DVR, UNISURF): samples t_{k+1} = t_k + h_k from t_min, the last one clamped to
    t_max (both clipped to the scene's ray bounds when ``bounds`` is set: :func:`clip_to_bounds`).
    The step h_k is the step rule's (``rule``).  :class:`ConstantStep` (the ``march_*`` methods):
    h_k = ``step``; a surface crossed twice within one step (a feature thinner than the step) is
    not seen by the samples, and the march's answer is certified against that by the frontier of
    its samples' spheres (:class:`ConstantStep`).

    :class:`CertifiedStep` (IDR-style hybrid, :meth:`CertifiedStep.size`): over-relaxed steps
    h_k = 0.9 · 2r_k/(1 + σ_k), r_k = |φ(t_k)|/L and σ_k the secant's slope over the last step
    (Keinert et al., "Enhanced Sphere Tracing", 2014), and a crossing step ``extrapolate`` × the
    secant's distance to its zero once the stretch it leaves uncertified is predicted within
    ``GATE`` · ``min_step``; below the slope ``PASSING_SLOPE`` a forced step Δ_k ∈ [``min_step``,
    ``overstep``].  A step longer than r_k is *certified* free of surface when the unbounding
    spheres of its ends overlap, r_k + r_{k+1} ≥ h_k (every point of the step is then within r of
    one end, where |φ| > 0).  An uncertified step without a sign change is rejected (the ray stays
    at t_k) and Δ_k halves, down to ``min_step``, where it stands uncertified: the *frontier* (the
    end of the stretch certified spheres covered from the start) stops there (state ``g``), a
    MISS is then UNCERTIFIED, and so is a crossing more than ``min_step`` past it.  A crossing
    step proves a root, not the first: its bracket is refined, then certified (stage
    ``step_certify``, :meth:`_certify`): CONVERGED when the frontier reaches ``min_step`` before
    the bracket, so the depth is within ``min_step`` + ``xtol`` of the first crossing.  A landing
    within φ's rounding of 0 is probed past once (state ``pl``).

    Ladder steps (``ladder`` = K > 1): after ``ladder_after`` marching steps (for a certifying
    rule, only once past its frontier by ``min_step``, where no crossing can be certified any
    more: nearer, the ladder's forced spacing would stand uncertified and flag the crossing, or
    pass a thin one) a ray marches K steps per loop step — K samples at a common spacing
    evaluated together, the pairs judged in order as single steps are (:meth:`step_ladder`),
    each a step against ``max_steps``.  The rays that need them (grazing rays;
    constant-step marching over long empty stretches) need hundreds to thousands of steps, and
    a loop step on few rays costs its per-call overhead whatever their number.  Every sample
    counts in ``evals``.

    Refinement of the bracket [a, b] (φ(a)φ(b) < 0) by the ``refiner``, one evaluation per
    iteration: :class:`Bisect` (midpoint; linear, ratio 1/2), :class:`Secant` on the last two
    iterates (order (1+√5)/2 near a simple root), :class:`Newton` t ← t − φ/φ' with
    φ' = ⟨∇φ, d⟩ (order 2).
    Safeguards (Brent; rtsafe, Numerical Recipes §9.4): an iterate outside the bracket, or one
    proposed when the bracket did not halve over the last three steps, is replaced by the
    midpoint, so every variant converges at worst at a third of bisection's rate; a step shorter
    than xtol/2 is lengthened to xtol/4 beyond the predicted root, so that secant and Newton,
    which close in from one side, also close the bracket.  **Converged only when certified**:
    φ = 0 exactly at an iterate, a sign-change bracket no wider than ``xtol``, or a bracket
    whose ends are adjacent floats (far from the origin ``xtol`` can be below the float
    spacing).  The reported ``t`` lies in that bracket: the last iterate (bisection), or the
    zero of the chord through the last two iterates (secant, Newton), which after a lengthened
    step are the bracket's ends.  For a certifying rule the refiner's bracket, whose sides are
    the signs of φ as computed, is not the certificate: a closed bracket is an answer only once
    the *certified* bracket [A, B] (from resolved samples only, :meth:`_bracket_sample`) is
    within :meth:`closing_width`, else after verification (:meth:`_verify`).  A marching step whose sign change spans ≤ ``xtol`` is
    converged at once.  Every marching and ladder step of the hybrid, and of constant-step
    marching where the scene declares a bound (``ConstantStep.check_inv_lip``), checks it: a step whose ends
    differ by more than L·h (beyond rounding, :func:`lipschitz_violated`) ends the ray with
    LIPSCHITZ_VIOLATED (t = NaN); a hybrid step leaving the ray bounds is evaluated where it
    ends (within ``t_max``) so that a step over thin surface under a false L is seen.
    ``max_steps`` bounds marching plus refinement steps.
    """

    rule: ConstantStep | CertifiedStep
    refiner: Bisect | Secant | Newton
    xtol: float
    max_steps: int
    t_min: float
    t_max: float
    bounds: Any = None  # the scene whose ray_bounds clip the search (None: all of [t_min, t_max])
    # off by default, the plain algorithm; the methods' defaults are their knobs' (impls.methods)
    ladder: int = 0  # samples per ladder step (≤ 1: no ladder stage)
    ladder_after: int = 0  # marching steps before a ray goes on in ladder steps
    scale: float = 0.0  # the scene's offset and extent, for the check's rounding slack (lipschitz_violated)
    gain: float = 1.0  # the scene's rounding gain, on that slack (lipschitz_violated)
    resolve: bool = False  # φ is a distance bound: its rounding near the surface is L·(point's rounding) (resolution)
    check_inside: bool = False  # L is a declaration taken on trust: check it inside every step (mid_probe)

    @property
    def stages(self) -> tuple[str, ...]:
        march = ("step_march", "step_ladder") if self.ladder > 1 else ("step_march",)
        return march + (("step_refine", "step_certify") if self.rule.certifies else ("step_refine",))

    @property
    def search_stages(self) -> int:
        """The number of leading stages that search for a crossing (marching, then the ladder);
        the later ones refine and certify the bracket it found.  A masked driver compacts only the
        searching stages level by level and runs the others once on the whole chunk afterwards
        (:func:`impls.jax.driver.run_loop`)."""
        return 2 if self.ladder > 1 else 1

    @property
    def deriv(self) -> bool:
        return self.refiner.deriv

    @property
    def verifies(self) -> bool:
        """Whether a closed bracket's answer is checked against the *certified* bracket [A, B]
        (:meth:`_bracket_sample`, :meth:`_verify`): always for a certifying rule; for a constant
        step where φ's rounding is modelled (a bound L to put it in depth units, a distance bound's
        gain ``rg`` > 0), since there the refiner's signs may be rounding's.  Without a model
        only φ = 0 is unresolved, and a bracket of computed signs is the certificate."""
        return self.rule.certifies or (self.rule.check_inv_lip is not None and self.rg > 0.0)

    def reads(self, stage: str) -> frozenset[str]:
        """The state entries the step of ``stage`` reads, all that a compacting driver carries
        for it (:mod:`impls.core.driver`): the iterate, its counters and, for marching, the ray's
        end, for refinement the bracket, plus what the step rule and the refiner hold.
        ``status`` and ``phase`` are not among them: every step writes them afresh."""
        keys = frozenset({"t", "f", "iterations", "evals", "mag"}) | self.refiner.holds(
            "step_refine" if stage == "step_certify" else stage)
        if stage in ("step_refine", "step_certify"):
            if self.rule.certifies:
                return keys | {"a", "b", "fa"} | CERTIFY_STATE
            return keys | {"a", "b", "fa"} | self.rule.holds(stage) | (VERIFY_STATE if self.verifies else frozenset())
        return keys | {"hi"} | self.rule.holds(stage)

    def init(self, xp, o, d, ev, start=None):
        t, hi, status = self.start(xp, o, d) if start is None else start
        f, df, cost = ev(o, d, t, self.deriv)
        # (|o|₁ + scale rides in the state, as in SphereTrace: the steps read it on every iteration)
        s = {"t": t, "f": f, "p": t, "fp": f, "a": t, "fa": f, "b": t, "hi": hi, "mag": _magnitude(xp, o, self.scale),
             "phase": xp.zeros_like(o[:, 0], dtype=xp.int32), "status": status,
             "iterations": xp.zeros_like(o[:, 0], dtype=xp.int32), "evals": xp.astype(status == IN, xp.int32) * cost}
        if self.deriv:
            s["df"] = df
        s.update(self.rule.init(xp, t))
        if not isinstance(self.refiner, Bisect):
            s["wq"] = xp.full_like(t, math.inf)  # bracket width at the last check (set on a crossing)
        unres = None
        if self.rule.certifies:
            f, unres = _outside_start(xp, self, f, t, s["mag"], self.rule.inv_lip)
            s.update(f=f, fp=f, fa=f)
            # the certification of a bracket's crossing as the first (step_refine): set on a crossing
            s.update(u=t, cp=t, fcp=f, kap=xp.ones_like(t), cm=xp.zeros_like(f, dtype=xp.bool))
            # the certified bracket [A, B] and its verification (_verify): set on a crossing
            s.update(A=t, B=t, vm=xp.zeros_like(f, dtype=xp.bool), zl=t, zr=t)
        elif self.verifies:
            # the certified bracket [A, B] of a constant-step march's crossing and its verification
            s.update(A=t, B=t, vm=xp.zeros_like(f, dtype=xp.bool), zl=t, zr=t)
        # a certifying rule starts only from a resolved point (a start on the surface to rounding
        # is UNCERTIFIED); a constant-step march from φ = 0 exactly shows no side either: the first
        # crossing lies strictly after the start (reference.scene.first_hit_from_intervals), and
        # whether the ray leaves the surface into the solid or out of it is not known, so it too is
        # UNCERTIFIED at once (it was CONVERGED at t_min, a depth the reference does not have)
        s["status"] = _init_status(xp, status, f, xp.zeros_like(f, dtype=xp.bool), (f == 0) if unres is None else unres)
        return s

    # The stage steps assume every row they are given is IN_PROGRESS in their stage (the
    # compacting drivers pass only those; the masked jax driver discards the other rows' update),
    # so statuses are set without re-testing the old one, and they leave a finished ray's t at
    # its last point (MISS, NON_FINITE: the drivers report it through final_t).  Bracket
    # invariant: a ≤ b (marching goes forward from t_min and refinement keeps c in [a, b]).

    def step_march(self, xp, s, o, d, ev):
        t, f, hi = s["t"], s["f"], s["hi"]
        rule = self.rule
        mag = s["mag"]
        # certified radius (|φ|/L less φ's rounding) at t
        rc = certified_radius(xp, f, t, rule.inv_lip, mag, self.rg) if rule.certifies else None
        r, h = rule.size(xp, s, t, f, rc)
        t_n = rule.end(xp, t, h, hi, self.t_max)
        f_n, df_n, cost = ev(o, d, t_n, self.deriv)
        zero = f_n == 0
        fin = xp.isfinite(f_n)
        beyond = (f_n == math.inf) & (hi == math.inf)  # (as in SphereTrace.step: past every finite depth)
        cross = fin & (zero | ((f_n > 0) != (f > 0)))
        rc_n = unres = None
        if rule.certifies:
            # certified radius at t_n; a landing within φ's rounding of 0 (in the
            # range) shows no side: no crossing is taken from it.  The ray stays and probes once
            # min_step past it (a step that lands on the surface, as sphere tracing does head-on,
            # then brackets it); a second such landing ends the ray UNCERTIFIED there
            r_n, res_n = rule.radius(xp, f_n), resolution(xp, t_n, mag, self.rg)
            rc_n = xp.maximum(r_n - res_n, 0.0)  # (certified_radius and unresolved, sharing their terms)
            unres = (r_n <= res_n) & (t_n <= hi)
            cross = cross & ~unres
            retry = unres & (s["pl"] == 0)
            unres = unres & ~retry
        # at hi, or past every finite depth (t_max = inf and no ray bound): the ray left
        gone = (t_n >= hi) | ~xp.isfinite(t_n) | beyond
        miss = ~cross & gone
        # converged at once: a bracket no wider than xtol, or φ = 0 exactly (a point that is
        # unresolved for either rule: the verdicts below make it UNCERTIFIED)
        conv = cross & (zero | (t_n - t <= self.xtol))
        nonf = ~fin & xp.isfinite(t_n) & ~beyond
        # the step's two ends are evaluated: a slope above the declared L shows it is false here
        lipv = None if rule.check is None else lipschitz_violated(xp, f, f_n, t, t_n, rule.check, mag, self.gain) & ~beyond
        if self.check_inside and rule.certifies:
            inside, extra = mid_probe(xp, self, o, d, ev, t, f, t_n, f_n, rule.inv_lip, mag)
            lipv, cost = lipv | (inside & ~beyond), cost + extra
        t_land = t_n
        ok, new, loose = rule.judge(xp, s, cross, rc, rc_n, h, t_n)
        if rule.certifies:  # a landing to probe past: the ray stays
            # a rejected plain step (h ≤ r, rejected by rounding alone): the certified radius next
            new["dl"] = xp.where(ok | retry | (h > r), new["dl"], xp.zeros_like(new["dl"]))
            ok, loose = ok & ~retry, loose & ~retry
            # (the inner select's 0 is an array of the state's dtype: with two Python floats torch and
            # array_api_compat make tensors of their default dtype and then reconcile dtypes, on every step)
            new["pl"] = xp.where(retry, (t_land - t) + rule.min_step,
                                 xp.where(s["pl"] != 0, -1.0, xp.zeros_like(s["pl"])))
        if ok is not None:  # a step that does not stand: the ray stays where it was
            miss = miss & ok
            t_n, f_n = xp.where(ok, t_n, t), xp.where(ok, f_n, f)
            if self.deriv:
                df_n = xp.where(ok, df_n, s["df"])
        iters = s["iterations"] + 1
        if rule.certifies:
            # a MISS is certified only if no step stood uncertified on the way; a crossing is the
            # first to within min_step only if the first such step began within min_step of it
            g = xp.where(loose & (s["g"] == math.inf), t + rc, s["g"])
            unc_miss = miss & (g < math.inf)
            status = _verdict(xp, nonf, conv, iters >= self.max_steps, miss & ~unc_miss, lipv,
                              unc=unc_miss | unres | (conv & (g + rule.min_step < t)))
            t_n = xp.where(unc_miss, math.inf, xp.where(unres, t_land, t_n))
            # the frontier: the end of the stretch certified spheres covered from the start on
            new.update(g=g, u=xp.minimum(t + rc, g), cp=t, fcp=f, kap=xp.ones_like(t), cm=xp.zeros_like(cross),
                       # a crossing's ends are resolved (an unresolved landing is no crossing): the
                       # first crossing of the bracket lies between their spheres
                       A=t + rc, B=t_land - rc_n, vm=xp.zeros_like(cross), zl=t, zr=t)
        else:
            g = s["g"]
            inv = rule.check_inv_lip
            if inv is None:  # (no bound, no rounding model: only φ = 0 exactly shows no side)
                un0, un1 = f == 0, zero
            else:
                rc0 = certified_radius(xp, f, t, inv, mag, self.rg)
                rc1 = certified_radius(xp, f_n, t_n, inv, mag, self.rg)
                # unresolved: |φ|/L within φ's rounding, certified radius 0 (unresolved())
                un0, un1 = rc0 == 0, rc1 == 0
                if rule.cover:
                    loose = ~cross & ~rule.covered(xp, rc0, rc1, t_n - t)
                    g = xp.where(loose & (g == math.inf), t + rc0, g)
                if self.verifies:
                    # a crossing's ends are resolved (else it is UNCERTIFIED): the crossing of φ itself
                    # lies between them, and under the bound the steps check, between their spheres
                    new.update(self._march_bracket(xp, t, rc0, t_n, rc1))
            status, unc_miss, back = self._march_verdict(xp, g, cross, conv, miss, nonf, lipv, iters, un0, un1, t)
            t_n = xp.where(unc_miss, math.inf, xp.where(back, t, t_n))
            new["g"] = g
        # on to refinement (the last stage: 1, or 2 after the ladder) on a crossing, else (with a
        # ladder stage) to the ladder after ladder_after steps
        to_refine = xp.astype(cross, xp.int32)
        # (a certifying rule's ray goes on in ladder steps only once it is past its frontier g by
        # min_step, where no crossing can be certified any more (CONVERGED needs the bracket within
        # min_step of g): before that, the ladder's forced spacing, without the crossing step, passed
        # thin crossings that single steps find (mesh.blob.grazing.1e-9: 19 of 256 hits certified
        # against 87), and it would stand uncertified before every crossing near a surface)
        to_ladder = iters >= self.ladder_after
        if rule.certifies:
            to_ladder = to_ladder & (t_n > new["g"] + rule.min_step)
        phase = xp.astype(cross | to_ladder, xp.int32) + to_refine if self.ladder > 1 else to_refine
        # on a crossing the bracket is [a, b] = [t, t_n] and the secant starts from (p, t) = (t, t_n);
        # for other rows a, b are overwritten before they are used
        new.update(t=t_n, f=f_n, p=t, fp=f, a=t, fa=f, b=t_n, phase=phase, status=status, iterations=iters,
                   evals=s["evals"] + cost)
        new.update(self.refiner.on_bracket(xp, t_n - t))
        if self.deriv:
            new["df"] = df_n
        return _typed(xp, dict(s, **new), s)

    def _march_verdict(self, xp, g, cross, conv, miss, nonf, lipv, iters, un0, un1, t0):
        """A constant-step march's status after the step (or ladder pair) from ``t0`` that the ray
        ends on (:class:`ConstantStep`): a MISS only with the frontier ``g`` at inf; a crossing
        closed at once only if ``g`` reaches within a step of ``t0``; a sign change to or from an
        unresolved end (``un0``, ``un1``: it shows no side; a ray lying in a face plane to
        rounding has φ = 0 along it) proves no crossing.  Returns ``(status, unc_miss, back)``:
        the uncertified MISSes (depth inf) and the rays UNCERTIFIED at the step's start (its
        start unresolved, its end not)."""
        un = cross & (un0 | un1)
        unc_miss = miss & (g < math.inf)
        late = conv & self.rule.late(xp, g, t0)
        status = _verdict(xp, nonf, conv, iters >= self.max_steps, miss & ~unc_miss, lipv, unc=unc_miss | late | un)
        return status, unc_miss, un & ~un1

    def step_ladder(self, xp, s, o, d, ev):
        """``ladder`` marching steps in one loop step, for rays still marching after
        ``ladder_after`` steps (grazing rays: a near miss at distance δ from a surface of radius
        of curvature ρ costs about (π/2)√(2ρ/δ) certified steps, each a loop step whose cost is
        per-call overhead once few rays are left).

        Samples t_j = t + j·h, j = 1 … K (clamped to ``hi``), with h = max(|φ(t)|/L, Δ) (hybrid)
        or the constant step, are evaluated together; the pairs (t_{j−1}, t_j) are then judged
        in order exactly as single marching steps are (a sign change brackets the surface; in the
        hybrid a pair must otherwise be certified by overlapping unbounding spheres or be no
        longer than ``min_step``).  The ray ends at the first pair that crosses (bracket), is not
        finite (NON_FINITE) or, in the hybrid, is not certified (the ray moves to that pair's
        start, the last certified point); with no such pair it moves to t_K (MISS at ``hi``).
        Every sample counts as an evaluation, including those after the pair the ray stops at;
        every pair judged is one iteration (step) against ``max_steps``, and pairs past the
        budget left are not judged, so a ladder changes no status a budget decides.  Δ doubles
        after a ladder with no stop and halves after one that stops in its first half, within
        [``min_step``, ``overstep``]."""
        t, f, hi = s["t"], s["f"], s["hi"]
        m, k = t.shape[0], self.ladder
        rule = self.rule
        mag = s["mag"]
        rc = certified_radius(xp, f, t, rule.inv_lip, mag, self.rg) if rule.certifies else None
        r, h = rule.ladder_size(xp, s, t, f, rc)
        j = xp.asarray(np.arange(1, k + 1), dtype=t.dtype, device=_device(t))
        T = xp.minimum(t[:, None] + h[:, None] * j[None, :], hi[:, None])
        F, DF, cost = ev(_repeat_rays(xp, o, k), _repeat_rays(xp, d, k), xp.reshape(T, (m * k,)), self.deriv)
        F = xp.reshape(F, (m, k))
        Tp = xp.concat([t[:, None], T[:, :-1]], axis=1)
        Fp = xp.concat([f[:, None], F[:, :-1]], axis=1)
        cross = (F == 0) | ((F > 0) != (Fp > 0))
        finite = xp.isfinite(F)
        if rule.certifies:
            R = certified_radius(xp, F, T, rule.inv_lip, mag[:, None], self.rg)
            Rp = xp.concat([rc[:, None], R[:, :-1]], axis=1)
            # a sample within φ's rounding of 0 shows no side: the ray stops there, UNCERTIFIED
            unresF = unresolved(xp, F, T, rule.inv_lip, mag[:, None], self.rg) & (T <= hi[:, None])
            cross = cross & ~unresF
            stands, sure = rule.ladder_certified(xp, Rp, R, T, Tp, hi, h)
            event = cross | ~finite | ~stands | unresF
        else:
            event = cross | ~finite
        if rule.check is not None:
            violated = lipschitz_violated(xp, Fp, F, Tp, T, rule.check, mag[:, None], self.gain)
            event = event | violated
        # max_steps counts steps, a ladder's pairs one by one, up to the first that reaches hi (the
        # samples past it repeat hi): the pairs past the budget left are evaluated (in evals) but not
        # judged, and a ray with no event before them ends on the last pair it may take, MAX_ITER
        # (the same steps and statuses as without a ladder)
        left = self.max_steps - s["iterations"]
        within = xp.asarray(np.arange(k), dtype=left.dtype, device=_device(t))[None, :] < left[:, None]
        event = event & within
        ends = event | ((T >= hi[:, None]) & within)
        first = xp.argmax(xp.astype(ends, xp.int8), axis=1)
        last = xp.astype(xp.minimum(left, k) - 1, first.dtype)
        e = xp.where(xp.any(ends, axis=1), first, last)[:, None]  # the first event's pair, or the last taken
        stopped = xp.take_along_axis(event, e, axis=1)[:, 0]

        def at(a):
            return xp.take_along_axis(a, e, axis=1)[:, 0]

        Te, Fe, Tpe, Fpe = at(T), at(F), at(Tp), at(Fp)
        cross_e = stopped & at(cross)
        beyond_e = stopped & (Fe == math.inf) & (hi == math.inf)  # (as in SphereTrace.step)
        nonf = stopped & ~at(finite) & xp.isfinite(Te) & ~beyond_e
        lipv = stopped & at(violated) & ~beyond_e if rule.check is not None else None
        onto = cross_e | ~stopped  # the ray moves onto sample e; otherwise it stays at e's start
        miss = (~stopped & (Te >= hi)) | ~xp.isfinite(Te) | beyond_e
        iters = s["iterations"] + xp.astype(e[:, 0], s["iterations"].dtype) + 1  # the pairs judged
        new = {}
        if rule.certifies:
            Rpe = at(Rp)
            conv = cross_e & (Te - Tpe <= self.xtol)
            # pairs the ray stepped over that stood uncertified (≤ min_step): the first one's start
            # is where the covered stretch ends (g, as in step_march)
            j = xp.asarray(np.arange(k), device=_device(t))[None, :]
            taken = (j < e) | ((j == e) & onto[:, None])
            loose = stands & ~sure & ~cross & taken
            fl = xp.argmax(xp.astype(loose, xp.int8), axis=1)[:, None]
            g_l = xp.take_along_axis(Tp, fl, axis=1)[:, 0] + xp.take_along_axis(Rp, fl, axis=1)[:, 0]
            g = xp.where(xp.any(loose, axis=1) & (s["g"] == math.inf), g_l, s["g"])
            unc_miss = miss & (g < math.inf)
            unres_e = stopped & at(unresF)
            status = _verdict(xp, nonf, conv, iters >= self.max_steps, miss & ~unc_miss, lipv,
                              unc=unc_miss | unres_e | (conv & (g + rule.min_step < Tpe)))
            t_new = xp.where(unc_miss, math.inf, xp.where(unres_e, Te, xp.where(onto, Te, Tpe)))
            new.update(g=g, u=xp.minimum(Tpe + Rpe, g), cp=Tpe, fcp=Fpe, kap=xp.ones_like(t), cm=xp.zeros_like(onto),
                       A=Tpe + Rpe, B=Te - at(R), vm=xp.zeros_like(onto), zl=t, zr=t)
        else:
            conv = cross_e & ((Fe == 0) | (Te - Tpe <= self.xtol))
            g = s["g"]
            inv = rule.check_inv_lip
            if rule.cover:
                # the pairs the ray stepped over, judged as single steps are (step_march); the
                # first uncovered one's start sphere ends the frontier
                R = certified_radius(xp, F, T, inv, mag[:, None], self.rg)
                Rp = xp.concat([certified_radius(xp, f, t, inv, mag, self.rg)[:, None], R[:, :-1]], axis=1)
                j = xp.asarray(np.arange(k), device=_device(t))[None, :]
                taken = (j < e) | ((j == e) & onto[:, None])
                loose = ~cross & ~rule.covered(xp, Rp, R, T - Tp) & taken
                fl = xp.argmax(xp.astype(loose, xp.int8), axis=1)[:, None]
                g_l = xp.take_along_axis(Tp, fl, axis=1)[:, 0] + xp.take_along_axis(Rp, fl, axis=1)[:, 0]
                g = xp.where(xp.any(loose, axis=1) & (g == math.inf), g_l, g)
                rc0, rc1 = at(Rp), at(R)
                un0, un1 = rc0 == 0, rc1 == 0  # (as in step_march, on the event pair's ends)
            elif inv is None:
                un0, un1 = Fpe == 0, Fe == 0
            else:
                rc0 = certified_radius(xp, Fpe, Tpe, inv, mag, self.rg)
                rc1 = certified_radius(xp, Fe, Te, inv, mag, self.rg)
                un0, un1 = rc0 == 0, rc1 == 0
            if self.verifies:
                new.update(self._march_bracket(xp, Tpe, rc0, Te, rc1))
            status, unc_miss, back = self._march_verdict(xp, g, cross_e, conv, miss, nonf, lipv, iters, un0, un1, Tpe)
            t_new = xp.where(unc_miss, math.inf, xp.where(onto & ~back, Te, Tpe))
            new["g"] = g
        f_new = xp.where(onto, Fe, Fpe)
        # the ladder is stage 1, refinement stage 2
        new.update(t=t_new, f=f_new, p=Tpe, fp=Fpe, a=Tpe, fa=Fpe, b=t_new,  # b = Te where crossed
                   phase=xp.astype(cross_e, xp.int32) + 1, status=status, iterations=iters,
                   evals=s["evals"] + cost * k)
        new.update(self.refiner.on_bracket(xp, Te - Tpe))
        new.update(rule.ladder_adapt(xp, s, stopped, cross_e, e[:, 0], k))
        if rule.certifies:
            # a first pair that is a plain step (h ≤ r) rejected by rounding alone: the ray steps its
            # certified radius next (as in step_march)
            plain_rejected = stopped & ~cross_e & (e[:, 0] == 0) & ~at(stands) & (h <= r)
            new["dl"] = xp.where(plain_rejected, xp.zeros_like(new["dl"]), new["dl"])
        if self.deriv:
            DF = xp.reshape(DF, (m, k))
            new["df"] = xp.where(onto, at(DF), at(xp.concat([s["df"][:, None], DF[:, :-1]], axis=1)))
        return _typed(xp, dict(s, **new), s)

    def _refine_step(self, xp, s, o, d, ev, c=None):
        """The refiner's step on the bracket [a, b] (at ``c`` where given): ``(new state entries,
        c, φ(c), same_a, closed)``."""
        t, f, a, b = s["t"], s["f"], s["a"], s["b"]
        mid = 0.5 * (a + b)
        i2 = s["iterations"] % 3 == 0  # a check of the bracket's progress (see the safeguards)
        prop = self.refiner.propose(xp, s, t, f, a, b, mid, i2, self.xtol)
        c = prop if c is None else c(prop)
        f_c, df_c, cost = ev(o, d, c, self.deriv)
        # fa is φ at the bracket's first end when it was formed: a moves only to points of φ's sign
        # there, so that sign (all that is used) never changes and fa, fb need no updates
        same_a = (f_c > 0) == (s["fa"] > 0)
        # φ(c) = 0 exactly closes the bracket at c itself, [c, c]: left at [a, c] (or [c, b]), its
        # far end could lie before other crossings of the bracket, and the certification stage
        # (_certify), which covers the stretch up to the bracket's start, would then pass them and
        # call c the first (hybrid_secant, 256² rays: a thin slab skipped, CONVERGED at the wall behind)
        exact = f_c == 0
        na = xp.where(same_a | exact, c, a)
        nb = xp.where(same_a & ~exact, b, c)
        # closed: a root found exactly, a sign-change bracket no wider than xtol, or one whose ends
        # are adjacent floats (the midpoint rounds to an end: no float lies between them)
        nmid = 0.5 * (na + nb)
        closed = (f_c == 0) | (nb - na <= self.xtol) | (nmid <= na) | (nmid >= nb)
        t_out = self.refiner.report(xp, c, f_c, t, f, na, nb, closed)
        new = dict(t=t_out, f=f_c, p=t, fp=f, a=na, b=nb, iterations=s["iterations"] + 1, evals=s["evals"] + cost)
        new.update(self.refiner.after(xp, s, i2, a, b, df_c))
        if self.verifies:
            new.update(self._bracket_sample(xp, s, c, f_c, same_a))
        return new, c, f_c, same_a, closed

    def _bracket_sample(self, xp, s, c, f_c, same_a) -> dict:
        """The certified bracket [A, B] after a sample (c, φ(c)) in it: a resolved sample of the
        start's side moves A to c + r_c, one of the other side B to c − r_c (r_c its certified
        radius, :func:`certified_radius`); an unresolved one moves neither.  The refiner's bracket
        [a, b] takes its sides from the sign of the computed φ, also where that sign is rounding;
        [A, B] only from signs that are proved, so a crossing of φ itself lies in it.  (Where φ's
        rounding is not modelled, ``rg`` = 0, only φ = 0 is unresolved, and inside a bracket of
        resolved signs it is taken as the root, [c, c], as sphere tracing takes it.)"""
        rule = self.rule
        r_c, unres = radius_and_unresolved(xp, f_c, c, rule.inv_lip if rule.certifies else rule.check_inv_lip,
                                           s["mag"], self.rg)
        A = xp.where(~unres & same_a, xp.maximum(s["A"], c + r_c), s["A"])
        B = xp.where(~unres & ~same_a, xp.minimum(s["B"], c - r_c), s["B"])
        if self.rg == 0.0:
            A, B = xp.where(f_c == 0, c, A), xp.where(f_c == 0, c, B)
        return dict(A=A, B=B)

    def _march_bracket(self, xp, t0, rc0, t1, rc1) -> dict:
        """A constant-step march's certified bracket of the crossing step [t0, t1], its ends moved
        by their certified radii ``rc0``, ``rc1`` (under the bound the steps check, as the hybrid's
        are: a bound found false voids the call's certificates, :func:`void_if_refuted`), and its
        verification state reset."""
        A = t0 + rc0
        return dict(A=A, B=t1 - rc1, vm=xp.zeros_like(rc0, dtype=xp.bool), zl=A, zr=A)

    def closing_width(self, xp, t, mag):
        """The widest certified bracket [A, B] a CONVERGED depth t may stand in, in depth units:
        max(``xtol``, 4·rounding, 2ε|t|) + 4ε|t| — the tolerance, or what the dtype resolves where
        that is more: φ's modelled rounding (:func:`resolution`, with the field's gain ``rg``: 0
        where φ is not a distance bound; along a ray meeting the surface at slope σ φ's sign is
        rounding over a stretch about 2·rounding/σ long) and two spacings of the floats at t
        (adjacent floats)."""
        at = xp.abs(t)
        res0 = 4.0 * resolution(xp, t, mag, self.rg)
        return xp.maximum(xp.maximum(res0, (2.0 * _eps(t)) * at), self.xtol) + (4.0 * _eps(t)) * at

    def _settle(self, xp, new, ok):
        """For the rows ``ok`` (a closed bracket whose certified bracket is within
        :meth:`closing_width`): the depth moved into [A, B] and the refiner's bracket set to it, so
        that the certification of the first crossing (:meth:`_certify`) covers the ray up to A."""
        A, B = new["A"], new["B"]
        t_c = xp.minimum(xp.maximum(new["t"], A), B)
        new["t"] = xp.where(ok, t_c, new["t"])
        new["a"] = xp.where(ok, xp.minimum(A, t_c), new["a"])
        new["b"] = xp.where(ok, xp.maximum(B, t_c), new["b"])

    def step_refine(self, xp, s, o, d, ev):
        """One refinement step of the bracket [a, b].  For a certifying step rule a closed bracket
        is CONVERGED when the march's frontier ``u`` reaches its start to within ``min_step``
        (:meth:`_certify`); otherwise the ray goes on to the certification stage with its answer.
        For a constant step a closed bracket the march's frontier leaves more than a step behind
        is UNCERTIFIED, with its depth (:meth:`ConstantStep.late`); where it verifies its answers
        (:attr:`verifies`) a closed bracket whose certified bracket is wider than the closing width
        is verified in this stage (a row in verification mode evaluates :meth:`_verify_sample`
        instead of the refiner's iterate, :meth:`_verify`)."""
        if self.verifies and not self.rule.certifies:
            return self._refine_verified(xp, s, o, d, ev)
        new, c, f_c, same_a, closed = self._refine_step(xp, s, o, d, ev)
        conv = closed
        unc = None
        if self.rule.certifies:
            # a closed bracket is an answer only once its certified bracket [A, B] is within the
            # closing width; else the answer is verified first (step_certify, _verify)
            ok = closed & (new["B"] - new["A"] <= self.closing_width(xp, new["t"], s["mag"]))
            self._settle(xp, new, ok)
            later = ok & (s["u"] + self.rule.min_step < new["a"])
            # a frontier stopped behind the last certified sample by a stretch that stood
            # uncertified cannot be moved on by samples from there: UNCERTIFIED, with its depth
            unc = later & (s["u"] < s["cp"])
            conv = ok & ~later
            verify = closed & ~ok
            new["cm"] = later & ~unc
            new["vm"] = verify
            new["zl"], new["zr"] = new["t"], new["t"]
            new["phase"] = xp.astype(later | verify, xp.int32) + (len(self.stages) - 2)
        else:
            # the march's frontier (ConstantStep): a closed bracket it leaves more than a step
            # behind is not certified the first crossing
            # (φ(c) = 0 exactly closes the bracket at [c, c]: its start is then c itself)
            unc = closed & self.rule.late(xp, s["g"], new["a"])
        new["status"] = _verdict(xp, ~xp.isfinite(f_c), conv, new["iterations"] >= self.max_steps, unc=unc)
        return _typed(xp, dict(s, **new), s)

    def _refine_verified(self, xp, s, o, d, ev):
        """:meth:`step_refine` of a constant-step march that verifies its answers (:attr:`verifies`):
        a closed bracket is CONVERGED once its certified bracket [A, B] is within the closing width
        (the depth moved into it), else verified (:meth:`_verify`); either way UNCERTIFIED, with
        its depth, where the march's frontier is more than a step behind its start."""
        mag, vm = s["mag"], s["vm"]
        width = self.closing_width(xp, s["t"], mag)
        probe, left = self._verify_sample(xp, s, width)
        new, c, f_c, same_a, closed = self._refine_step(xp, s, o, d, ev, c=lambda prop: xp.where(vm, probe, prop))
        ok = closed & ~vm & (new["B"] - new["A"] <= self.closing_width(xp, new["t"], mag))
        self._settle(xp, new, ok)
        verify = closed & ~vm & ~ok
        new.update(vm=vm, zl=s["zl"], zr=s["zr"])  # (_verify updates the rows in verification mode)
        conv_v, unc_v = self._verify(xp, s, new, c, f_c, same_a, left, width, mag)
        conv = xp.where(vm, conv_v, ok)
        # (φ(c) = 0 exactly closes the bracket at [c, c]: its start is then c itself)
        unc = xp.where(vm, unc_v, ok & self.rule.late(xp, s["g"], new["a"]))
        new["vm"] = xp.where(vm, new["vm"], verify)
        new["zl"], new["zr"] = xp.where(verify, new["t"], new["zl"]), xp.where(verify, new["t"], new["zr"])
        new["status"] = _verdict(xp, ~xp.isfinite(f_c), conv, new["iterations"] >= self.max_steps, unc=unc)
        return _typed(xp, dict(s, **new), s)

    def step_certify(self, xp, s, o, d, ev):
        """The certification stage (:meth:`_certify`): a row in certification mode (``cm``)
        evaluates a certification sample instead of the refiner's iterate; a row whose sample
        found an earlier crossing refines that bracket here, and is certified in turn."""
        mag = s["mag"]
        cm, vm = s["cm"], s["vm"]
        width = self.closing_width(xp, s["t"], mag)
        probe, left = self._verify_sample(xp, s, width)
        new, c, f_c, same_a, closed = self._refine_step(
            xp, s, o, d, ev,
            c=lambda prop: xp.where(vm, probe, xp.where(cm, self._certify_sample(xp, s, s["a"], mag), prop)))
        conv, unc = self._certify(xp, s, new, c, f_c, same_a, closed, mag)
        conv_v, unc_v = self._verify(xp, s, new, c, f_c, same_a, left, width, mag)
        conv, unc = xp.where(vm, conv_v, conv), xp.where(vm, unc_v, unc)
        # a certification sample is a step from the last certified sample cp: its two ends check the
        # bound as every marching step's do (and, for a bound taken on trust, its midpoint too)
        lipv = cm & lipschitz_violated(xp, s["fcp"], f_c, s["cp"], c, self.rule.inv_lip, mag, self.gain)
        if self.check_inside:
            inside, extra = mid_probe(xp, self, o, d, ev, s["cp"], s["fcp"], c, f_c, self.rule.inv_lip, mag)
            lipv = lipv | (cm & inside)
            # (every row of the stage was evaluated there, and counts it; only a certification
            # sample's step is checked)
            new["evals"] = new["evals"] + extra
        new["status"] = _verdict(xp, ~xp.isfinite(f_c), conv, new["iterations"] >= self.max_steps, lipv=lipv, unc=unc)
        return _typed(xp, dict(s, **new), s)

    def _certify_sample(self, xp, s, a, mag):
        """Where a row in certification mode evaluates next: an over-relaxed step from the last
        certified sample ``cp`` towards the bracket's end ``a`` (Keinert et al. 2014).  Where the
        surface is crossed at slope σ (in units of L), the unbounding spheres of cp and cp + h
        overlap while h ≤ 2ρ/(1 + σ), ρ the sphere's radius at cp; σ is estimated as ρ/(a − cp)
        (exact for a plane), and ``kap`` ∈ (0, 1] moves the step back towards ρ after a sample
        whose sphere did not overlap (a plain step, κ → 0, always does)."""
        rule = self.rule
        cp = s["cp"]
        rp = certified_radius(xp, s["fcp"], cp, rule.inv_lip, mag, self.rg)
        y = a - cp
        with _quiet(xp):
            sig = xp.minimum(rp / y, 1.0)
        h = rp + s["kap"] * (2.0 * rp / (1.0 + sig) - rp)
        return xp.minimum(cp + h, a)

    def _verify_sample(self, xp, s, width):
        """Where a row in verification mode (``vm``) evaluates next, and whether that is left of its
        answer t (:meth:`_verify`): in the larger of the two stretches not yet searched, [A, zl]
        and [zr, B], the point w/2 beyond the unresolved stretch [zl, zr] (w the closing width: the
        first sample, w/2 from t, brings that end within w/2 when it is resolved; a second one, w
        from t, shows [zl, zr] as wide as w when it is not), where that lies beyond the stretch's
        middle, else its middle (a bisection for where φ's sign stops being rounding)."""
        A, B, zl, zr = s["A"], s["B"], s["zl"], s["zr"]
        left, lo, hi = _verify_stretch(xp, A, B, zl, zr)
        mid = 0.5 * (lo + hi)
        out = xp.where(left, zl - 0.5 * width, zr + 0.5 * width)
        # (w/2 beyond [zl, zr] where that lies past the stretch's middle, seen from [zl, zr])
        c = xp.where(left, xp.where(out > mid, out, mid), xp.where(out < mid, out, mid))
        return c, left

    def _verify(self, xp, s, new, c, f_c, same_a, left, width, mag):
        """Verification of a closed bracket's answer t whose certified bracket [A, B] (a crossing
        of φ itself lies in it: :meth:`_bracket_sample`) is wider than the closing width w
        (:meth:`closing_width`): the refiner closed on samples whose sign was φ's rounding, so the
        crossing may lie outside its bracket.  [zl, zr] ∋ t is the stretch found unresolved so
        far; a row in verification mode (``vm``) samples the larger of [A, zl] and [zr, B], w/2
        beyond [zl, zr] or at its middle (:meth:`_verify_sample`), a search for the ends of the
        stretch where φ's sign is rounding.  Returns the rows CONVERGED and the rows that give up
        (UNCERTIFIED, with the depth t), and sets ``new`` for the rest.

        * An unresolved sample widens [zl, zr] to it.
        * A resolved sample of its side's sign (the start's left of t, the other right) moves that
          end of [A, B] past it (by its sphere).  Once B − A ≤ w the answer stands: t moves into
          [A, B], which becomes the bracket, and the row is CONVERGED, or certified the first
          crossing (:meth:`_certify`) where the march's frontier is more than ``min_step`` behind A.
        * A resolved sample of the other sign: the crossing lies beyond it, outside the bracket
          the refiner closed.  Refinement resumes on the bracket from that sample, [a, c] left of
          t (a at most A), [c, b] right of it (b at least B), from the secant through t and c.
        * The row gives up when [zl, zr] is as wide as w (no certified bracket within w can hold
          it), or when the stretch it would bisect has no float inside.

        Cost: nothing where the refiner's own samples certify the bracket (a resolved sample on
        each side near the crossing), a few samples where its last one is within φ's rounding of 0
        (measured in docs/methods.md)."""
        rule = self.rule
        vm, t = s["vm"], s["t"]
        A, B = new["A"], new["B"]
        unres = unresolved(xp, f_c, c, rule.inv_lip if rule.certifies else rule.check_inv_lip, mag, self.rg)
        ours = ~unres & (same_a == left)
        theirs = ~unres & (same_a != left)
        zl = xp.where(unres & left, xp.minimum(s["zl"], c), s["zl"])
        zr = xp.where(unres & ~left, xp.maximum(s["zr"], c), s["zr"])
        done = vm & ours & (B - A <= width)
        # (the next sample: the middle of the larger stretch left, which must hold a float)
        _, lo, hi = _verify_stretch(xp, A, B, zl, zr)
        mid = 0.5 * (lo + hi)
        give_up = vm & ~done & ~theirs & ((zr - zl >= width) | (mid <= lo) | (mid >= hi))
        t_c = xp.minimum(xp.maximum(t, A), B)
        if rule.certifies:
            later = done & (s["u"] + rule.min_step < xp.minimum(A, t_c))
            # (a frontier stopped behind the last certified sample: UNCERTIFIED, as in step_refine)
            give_up = give_up | (later & (s["u"] < s["cp"]))
            later = later & ~give_up
        else:  # a constant step's frontier more than a step behind the answer: UNCERTIFIED
            give_up = give_up | (done & rule.late(xp, s["g"], xp.minimum(A, t_c)))
            later = xp.zeros_like(done)
        # the rows that go on sampling, or stop: their answer and bracket stay
        stay = vm & ~theirs
        for k in ("t", "f", "p", "fp", "a", "b", "wq", "df"):
            if k in new and k in s:
                new[k] = xp.where(stay, s[k], new[k])
        new["t"] = xp.where(done, t_c, new["t"])
        new["a"] = xp.where(done, xp.minimum(A, t_c), new["a"])
        new["b"] = xp.where(done, xp.maximum(B, t_c), new["b"])
        # refinement resumes on the bracket beyond a sample of the other sign (the refiner's step on
        # it set a or b to it by its sign; the far end is kept at least as wide as [A, B])
        resume = vm & theirs
        new["t"], new["f"] = xp.where(resume, c, new["t"]), xp.where(resume, f_c, new["f"])
        new["p"], new["fp"] = xp.where(resume, t, new["p"]), xp.where(resume, s["f"], new["fp"])
        new["a"] = xp.where(resume & left, xp.minimum(s["a"], A), new["a"])
        new["b"] = xp.where(resume & ~left, xp.maximum(s["b"], B), new["b"])
        for k, v in self.refiner.on_bracket(xp, new["b"] - new["a"]).items():
            new[k] = xp.where(resume, v, new[k])
        new["vm"] = xp.where(vm, ~done & ~give_up & ~theirs, new["vm"])
        if rule.certifies:
            new["cm"] = xp.where(vm, later, new["cm"])
        new["zl"], new["zr"] = xp.where(vm, zl, new["zl"]), xp.where(vm, zr, new["zr"])
        return done & ~later & ~give_up, give_up

    def _certify(self, xp, s, new, c, f_c, same_a, closed, mag):
        """Certification that the bracket's crossing is the ray's first, for a certifying step
        rule; updates ``new`` (the step's state) and returns the rows CONVERGED and the rows that
        give up (UNCERTIFIED).

        The march proved no crossing before the frontier ``u`` (the end of the stretch certified
        spheres covered from the start, without a gap), and the crossing step proved one in
        [u, b].  A sample on the start's side whose sphere reaches back to the frontier extends
        it to its sphere's end.  A closed bracket is CONVERGED when u + ``min_step`` reaches its
        start ``a``: the first crossing then lies in [a − min_step, b], so the depth is within
        min_step + xtol of it (a pair of crossings with chord < min_step in that last stretch is
        what can be passed over).  Otherwise the row enters certification mode: its answer
        stays, and it samples from the last certified point towards ``a``
        (:meth:`_certify_sample`) until the frontier reaches it — or a sample shows the other
        sign: an earlier crossing, whose bracket [cp, c] refinement then takes up afresh — or the
        frontier crawls (a sphere under 1/``CERTIFY_REACH`` of what is left: a tangency) or a
        sample lands within φ's rounding of 0: then the row gives up, UNCERTIFIED with its
        answer's depth."""
        rule = self.rule
        cm, u, cp = s["cm"], s["u"], s["cp"]
        # a row refining here (an earlier crossing's bracket) closes as in step_refine: on a
        # certified bracket within the closing width, else it verifies its answer first
        # (rows in verification mode are left to _verify)
        free = ~cm & ~s["vm"]
        ok = closed & (new["B"] - new["A"] <= self.closing_width(xp, new["t"], mag))
        self._settle(xp, new, free & ok)
        verify = free & closed & ~ok
        closed = ok
        # a sample within φ's rounding of 0 shows no side: no earlier crossing is taken from it, and
        # it extends the frontier only as far as the min_step allowance reaches (its sphere is empty)
        rc, unres = radius_and_unresolved(xp, f_c, c, rule.inv_lip, mag, self.rg)
        side = (same_a & (f_c != 0)) | (cm & unres)
        earlier = cm & ~side
        # (to the rounding of the positions: a plain step from cp must stand)
        stands = side & (c - rc - u <= (4.0 * _eps(c)) * xp.abs(c))
        u_n = xp.where(stands, xp.maximum(u, c + rc), u)
        adv = stands & (c > cp)
        lo = xp.where(cm, s["a"], new["a"])
        certified = u_n + rule.min_step >= lo
        conv = xp.where(cm, ~earlier & certified, closed & certified)
        # a frontier that moves on by less than 1/CERTIFY_REACH of what is left to cover is near a
        # tangency (spheres of radius σ·distance, σ → 0): UNCERTIFIED rather than thousands of samples
        # (a sample within φ's rounding of 0, an empty sphere, likewise)
        give_up = cm & ~certified & ((stands & (rc * CERTIFY_REACH < lo - rule.min_step - u_n)) | unres)
        keep = cm & ~earlier  # certification goes on: the answer and its bracket stay
        restart = earlier  # refinement of [cp, c] from the secant (cp, fcp) → (c, f_c)
        for k in ("t", "f", "p", "fp", "a", "b", "wq", "df", "A", "B"):
            if k in new and k in s:
                new[k] = xp.where(keep, s[k], new[k])
        # the earlier crossing lies between the spheres of cp (certified) and of c (resolved)
        new["A"] = xp.where(restart, cp + certified_radius(xp, s["fcp"], cp, rule.inv_lip, mag, self.rg), new["A"])
        new["B"] = xp.where(restart, c - rc, new["B"])
        new["a"] = xp.where(restart, cp, new["a"])
        new["p"] = xp.where(restart, cp, new["p"])
        new["fp"] = xp.where(restart, s["fcp"], new["fp"])
        new["t"] = xp.where(restart, c, new["t"])
        new["f"] = xp.where(restart, f_c, new["f"])
        new["b"] = xp.where(restart, c, new["b"])
        for k, v in self.refiner.on_bracket(xp, c - cp).items():
            new[k] = xp.where(restart, v, new[k])
        new.update(u=u_n, cp=xp.where(adv, c, cp), fcp=xp.where(adv, f_c, s["fcp"]),
                   kap=xp.where(cm, xp.where(stands, xp.minimum(2.0 * s["kap"], 1.0), 0.5 * s["kap"]), s["kap"]),
                   cm=keep | (~cm & closed & ~certified), vm=verify, zl=new["t"], zr=new["t"])
        return conv, give_up


def _verify_stretch(xp, A, B, zl, zr):
    """(left, lo, hi): the larger of the two stretches a verification has not searched, [A, zl]
    (left) or [zr, B] (:meth:`MarchRefine._verify_sample`, :meth:`MarchRefine._verify`)."""
    left = zl - A >= B - zr
    return left, xp.where(left, A, zr), xp.where(left, zl, B)


#: the state a certifying rule's refinement stage keeps (:meth:`MarchRefine._certify`): the
#: frontier ``u``, the last certified sample ``cp`` and its φ ``fcp``, the certification step's
#: relaxation ``kap`` and the mode ``cm``; the certified bracket ``A``, ``B``
#: (:meth:`MarchRefine._bracket_sample`), the verification mode ``vm`` and the stretch found
#: unresolved ``zl``, ``zr`` (:meth:`MarchRefine._verify`)
CERTIFY_STATE = frozenset({"u", "cp", "fcp", "kap", "cm", "A", "B", "vm", "zl", "zr"})
#: what a constant-step march's refinement carries where it verifies its answers (:attr:`MarchRefine.verifies`):
#: the certified bracket, the verification's mode and stretch, and the last two iterates, which a row
#: in verification keeps (:meth:`MarchRefine._verify`) whatever its refiner
VERIFY_STATE = frozenset({"A", "B", "vm", "zl", "zr", "p", "fp"})

#: certification gives up (UNCERTIFIED) when a sample's sphere is under 1/this of the stretch left
#: to cover: at slope σ each sample covers about a factor (1 + σ)/(1 − σ), so this stops the rays
#: that would need more than about 32·ln(stretch/min_step) samples (σ < 1/64: near a tangency)
CERTIFY_REACH = 64.0


STATE_OUT = ("t", "status", "iterations", "evals")


def outputs(xp, state) -> dict:
    """The per-ray outputs :data:`STATE_OUT` of a state, ``t`` as reported (:func:`final_t`)."""
    out = {k: state[k] for k in STATE_OUT}
    out["t"] = final_t(xp, out["t"], out["status"])
    return out


def void_if_refuted(alg, out: dict) -> dict:
    """``out`` (a root finder's per-ray outputs, :func:`outputs`) with every certificate withdrawn
    where the bound it rests on is shown false: when ``alg`` takes the scene's Lipschitz bound L on
    trust (``alg.check_inside``, :func:`impls.core.methods_root.checks_inside`) and any ray of the
    call ended LIPSCHITZ_VIOLATED, each CONVERGED ray becomes UNCERTIFIED with its depth and each
    MISS UNCERTIFIED at t = inf.

    Why every ray: L is one claim about the whole field (|∇φ| ≤ L wherever the scene states it),
    and every CONVERGED ("the first crossing") and every MISS ("no crossing") is proved from it.  A
    violation seen on one ray refutes it for all of them, including rays whose own samples happened
    to agree with L: the per-ray checks see a false L only where it shows between a step's samples
    (a thin wall crossed obliquely under a 4× understated L passes every check of that ray, and its
    CONVERGED depth is the wall behind).  The library's own nodes carry bounds proved by their
    construction, where a violation can only be φ's rounding outrunning its model on that ray:
    they keep their other rays' certificates (``check_inside`` False), and so do the constant-step
    marchers, which rely on no bound.  Written with the outputs' own namespace (numpy, torch, or
    traced jax), so that every backend's driver shares it."""
    if not getattr(alg, "check_inside", False):
        return out
    import array_api_compat

    status = out["status"]
    xp = array_api_compat.array_namespace(status)
    refuted = xp.any(status == LIPV)
    void = refuted & ((status == CONV) | (status == MISS))
    return dict(out, status=xp.where(void, xp.asarray(UNC, dtype=status.dtype), status))
