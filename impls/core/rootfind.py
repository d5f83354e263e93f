"""Ray root finders as per-ray state machines: one φ evaluation per iteration per ray.

Each algorithm is a pair ``init(...) -> state`` and ``step(state, o, d) -> state`` on a dict of
per-ray arrays (leading dimension n), written with elementwise array-API operations only, in
the style of scipy's elementwise iterative methods (``scipy/_lib/_elementwise_iterative_
method.py``).  A backend's *loop driver* calls ``step`` while any ray has status IN_PROGRESS:
numpy and torch pass only the active rays (compaction), jax passes all rays and keeps the old
values of finished ones (masking).  Both give identical per-ray results.

Ray: x(t) = o + t d with |d| = 1, search interval [t_min, t_max].  φ is evaluated through the
backend's ``ev(o, d, t, deriv) -> (f, df, cost)`` where ``df = dφ/dt = ⟨∇φ, d⟩`` (only when
``deriv``) and ``cost`` is the number of φ evaluations per ray it used (``evals``).

Per-ray outputs: ``t`` (depth; ``inf`` for MISS, NaN for NON_FINITE, the last iterate for
MAX_ITER), ``status`` (:class:`impls.protocol.Status`), ``iterations`` and ``evals``.
"""

from __future__ import annotations

import dataclasses
import math

from ..protocol import Status

IN, CONV, MISS, MAXI, NONF, BAD = (int(s) for s in (Status.IN_PROGRESS, Status.CONVERGED, Status.MISS,
                                                     Status.MAX_ITER, Status.NON_FINITE, Status.BAD_INPUT))


def bad_rays(xp, o, d):
    """Rays with a non-finite origin or direction (BAD_INPUT)."""
    return ~(xp.all(xp.isfinite(o), axis=1) & xp.all(xp.isfinite(d), axis=1))


def _quiet(xp):
    """Silence numpy's divide warnings where a non-finite result is handled explicitly."""
    import contextlib

    import numpy as np

    return np.errstate(divide="ignore", invalid="ignore") if xp is np else contextlib.nullcontext()


def _typed(xp, new: dict, old: dict) -> dict:
    """``new`` with the dtypes of ``old`` (python scalars in ``where`` may promote, e.g. to int64
    in torch; loop carries and scatter targets need fixed dtypes)."""
    return {k: xp.astype(v, old[k].dtype, copy=False) for k, v in new.items()}


def _finish(xp, s, t_new, f_new, conv, iters, max_steps):
    """Common end of a step: NON_FINITE, CONVERGED, MAX_ITER, in this order of precedence."""
    status = s["status"]
    nonf = (status == IN) & ~xp.isfinite(f_new)
    status = xp.where(nonf, NONF, status)
    status = xp.where((status == IN) & conv, CONV, status)
    status = xp.where((status == IN) & (iters >= max_steps), MAXI, status)
    t_new = xp.where(nonf, math.nan, t_new)
    return status, t_new


# -- sphere tracing ----------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class SphereTrace:
    """Sphere tracing (Hart 1996; lecture 'Sphere Tracing') with optional over-relaxation.

    Step t ← t + ω|φ(x(t))|/L, L the scene's Lipschitz bound (``|φ|`` so a ray starting inside
    marches to its exit).  With ω > 1 (Keinert et al., "Enhanced Sphere Tracing", STAG 2014):
    if the unbounding spheres of two consecutive points do not overlap (r_k + r_{k−1} < t_k −
    t_{k−1}, r = |φ|/L) the relaxed step may have jumped over the surface, so the tracer goes
    back to the safe point t_{k−1} + r_{k−1} and continues with ω = 1; a point is accepted only
    when that test passes, so over-relaxation never tunnels.  Converged when |φ| ≤ tol; MISS
    when the next t exceeds t_max; MAX_ITER after ``max_steps`` steps.  One φ evaluation at
    t_min plus one per step (a step that leaves the range re-evaluates the last point: one
    evaluation per iteration keeps the loop shape fixed).
    """

    inv_lip: float
    tol: float
    max_steps: int
    omega: float
    t_min: float
    t_max: float

    def init(self, xp, o, d, ev):
        n = o.shape[0]
        t = xp.full_like(o[:, 0], self.t_min)
        bad = bad_rays(xp, o, d)
        f, _, cost = ev(o, d, t, False)
        s = {"t": t, "f": f, "t_prev": t, "r_prev": xp.zeros_like(t), "omega": xp.full_like(t, self.omega),
             "status": xp.astype(xp.where(bad, BAD, IN), xp.int32), "iterations": xp.zeros_like(o[:, 0], dtype=xp.int32),
             "evals": xp.full_like(o[:, 0], cost, dtype=xp.int32)}
        status, t = _finish(xp, s, t, f, xp.abs(f) <= self.tol, s["iterations"], self.max_steps + 1)
        s.update(status=status, t=t)
        return s

    def step(self, xp, s, o, d, ev):
        t, f, om = s["t"], s["f"], s["omega"]
        r = xp.abs(f) * self.inv_lip
        fail = (om > 1) & (r + s["r_prev"] < t - s["t_prev"])
        t_new = xp.where(fail, s["t_prev"] + s["r_prev"], t + om * r)
        t_prev = xp.where(fail, s["t_prev"], t)
        r_prev = xp.where(fail, s["r_prev"], r)
        om = xp.where(fail, xp.ones_like(om), om)
        out = t_new > self.t_max
        f_new, _, cost = ev(o, d, xp.where(out, t, t_new), False)
        iters = s["iterations"] + 1
        # accept a point only if its unbounding sphere overlaps the previous one (Keinert et al.)
        ok = ~((om > 1) & (xp.abs(f_new) * self.inv_lip + r_prev < t_new - t_prev))
        s2 = dict(s, status=xp.where(out, MISS, s["status"]))
        status, t_new = _finish(xp, s2, t_new, xp.where(out, f, f_new), (xp.abs(f_new) <= self.tol) & ok,
                                iters, self.max_steps)
        return _typed(xp, dict(t=xp.where(out, math.inf, t_new), f=f_new, t_prev=t_prev, r_prev=r_prev, omega=om,
                               status=status, iterations=iters, evals=s["evals"] + cost), s)


# -- marching to a sign change, then refinement ------------------------------------------------


@dataclasses.dataclass(frozen=True)
class MarchRefine:
    """March to the first sign change of φ along the ray, then refine the bracket.

    Marching (DVR, UNISURF): samples t_{k+1} = t_k + h_k from t_min, the last one clamped to
    t_max; ``h_k = min_step`` (constant) or, with ``inv_lip`` set (the IDR-style hybrid),
    h_k = max(|φ(t_k)|/L, min_step) — a sphere-tracing step that never shrinks below ``step``, so
    grazing rays (where sphere tracing converges only linearly) cross the surface in a few
    steps.  A surface crossed twice within one step (a feature thinner than ``min_step``) is not
    seen: that is marching's documented limit.

    Refinement of the bracket [a, b] (φ(a)φ(b) < 0), one evaluation per iteration:
    ``bisect`` (midpoint; linear, ratio 1/2); ``secant`` on the last two iterates (order
    (1+√5)/2 near a simple root); ``newton`` t ← t − φ/φ' with φ' = ⟨∇φ, d⟩ (order 2; the first
    refinement step is a secant step because φ' is not known at the bracket ends).  Secant and
    Newton iterates that leave the bracket are replaced by the midpoint (safeguard), so every
    variant converges.  Converged when φ = 0 exactly, the bracket is narrower than ``xtol``,
    or (secant/Newton) the last step was shorter than ``xtol``.  ``t`` is the last iterate.
    """

    refine: str  # "bisect" | "secant" | "newton"
    min_step: float
    inv_lip: float | None
    xtol: float
    max_steps: int
    t_min: float
    t_max: float

    @property
    def deriv(self) -> bool:
        return self.refine == "newton"

    def init(self, xp, o, d, ev):
        n = o.shape[0]
        t = xp.full_like(o[:, 0], self.t_min)
        bad = bad_rays(xp, o, d)
        f, df, cost = ev(o, d, t, self.deriv)
        zero = xp.zeros_like(t)
        s = {"t": t, "f": f, "df": zero if df is None else df, "a": t, "fa": f, "b": t, "fb": f, "p": t, "fp": f,
             "phase": xp.zeros_like(o[:, 0], dtype=xp.int32), "status": xp.astype(xp.where(bad, BAD, IN), xp.int32),
             "iterations": xp.zeros_like(o[:, 0], dtype=xp.int32), "evals": xp.full_like(o[:, 0], cost, dtype=xp.int32)}
        status, t = _finish(xp, s, t, f, f == 0, s["iterations"], self.max_steps + 1)
        s.update(status=status, t=t)
        return s

    def step(self, xp, s, o, d, ev):
        t, f = s["t"], s["f"]
        march = s["phase"] == 0
        # marching proposal
        h = self.min_step if self.inv_lip is None else xp.maximum(xp.abs(f) * self.inv_lip, self.min_step)
        t_m = xp.minimum(t + h, self.t_max)
        # refinement proposal
        a, b = s["a"], s["b"]
        mid = 0.5 * (a + b)
        if self.refine == "bisect":
            c = mid
        else:
            with _quiet(xp):  # f = fp or φ' = 0 give inf/NaN: replaced by the midpoint below
                c = t - f * (t - s["p"]) / (f - s["fp"])
                if self.refine == "newton":
                    c = xp.where(s["phase"] == 2, t - f / s["df"], c)
            lo, hi = xp.minimum(a, b), xp.maximum(a, b)
            # safeguard: outside the closed bracket → bisect.  (Closed: near convergence the secant
            # step can round to the bracket end itself; that is then a converged step, not a failure.)
            c = xp.where(xp.isfinite(c) & (c >= lo) & (c <= hi), c, mid)
        t_eval = xp.where(march, t_m, c)
        t_eval = xp.where(s["status"] == IN, t_eval, xp.zeros_like(t_eval))  # finished rays (masked drivers)
        f_new, df_new, cost = ev(o, d, t_eval, self.deriv)
        df_new = s["df"] if df_new is None else df_new
        # marching outcome: a sign change brackets a root
        cross = march & ((f_new == 0) | ((f_new > 0) != (f > 0)))
        miss = march & ~cross & (t_m >= self.t_max) & xp.isfinite(f_new)
        # refinement outcome: keep the sub-interval with the sign change
        same_a = (f_new > 0) == (s["fa"] > 0)
        na = xp.where(march, t, xp.where(same_a, c, a))
        nfa = xp.where(march, f, xp.where(same_a, f_new, s["fa"]))
        nb = xp.where(march, t_m, xp.where(same_a, b, c))
        nfb = xp.where(march, f_new, xp.where(same_a, s["fb"], f_new))
        width_ok = xp.abs(nb - na) <= self.xtol
        step_ok = (xp.abs(c - t) <= self.xtol) if self.refine != "bisect" else width_ok
        conv = (f_new == 0) | (~march & (width_ok | step_ok)) | (cross & width_ok)
        phase = xp.where(march, xp.where(cross, 1, 0), 2)
        phase = xp.astype(phase, xp.int32)
        iters = s["iterations"] + 1
        s2 = dict(s, status=xp.astype(xp.where(miss, MISS, s["status"]), xp.int32))
        status, t_out = _finish(xp, s2, t_eval, f_new, conv, iters, self.max_steps)
        t_out = xp.where(miss, math.inf, t_out)
        return _typed(xp, dict(t=t_out, f=f_new, df=df_new, a=na, fa=nfa, b=nb, fb=nfb, p=t, fp=f, phase=phase,
                               status=status, iterations=iters, evals=s["evals"] + cost), s)


STATE_OUT = ("t", "status", "iterations", "evals")


def outputs(state) -> dict:
    return {k: state[k] for k in STATE_OUT}
