"""scipy's elementwise Chandrupatla solver as the refiner of a constant-step marcher: a peer of
isobench's own bracket refiners (bisection, secant, Newton), method ``march_chandrupatla``.

The marching is isobench's (:class:`impls.core.rootfind.MarchRefine` with a
:class:`~impls.core.rootfind.ConstantStep` rule, ladder steps included: the same samples, the
same brackets, statuses and Lipschitz checks as ``march_bisect``); only the refinement stage
differs.  Where ``march_bisect`` shrinks a bracket one loop step at a time, the refinement stage
here hands every bracket the loop driver gives it to ``scipy.optimize.elementwise.find_root``
(Chandrupatla 1997: inverse quadratic interpolation where the last three points make it safe,
else bisection; superlinear near a simple root) in one call, which runs to completion.

Contract (φ along the ray t ↦ φ(o + t d), bracket [a, b] with φ(a)φ(b) < 0 from the march):

* scipy's tolerances: ``xatol = max(0, xtol − ε·M)``, ``xrtol = ε`` (M the largest |a|, |b| of
  the call, ε the dtype's), ``fatol = frtol = 0``.  scipy stops when its bracket is narrower than
  ``xatol + ε·|x_min|`` ≤ xtol (or, where xtol is below the float spacing, about one spacing) or
  φ = 0 exactly at an iterate.  (scipy's tolerances are scalars: one ray far from the origin
  in a call makes every ray of that call refine to about a float spacing, which costs a few
  iterations more and changes no status.)
* CONVERGED is decided here, from scipy's returned bracket ``(xl, xr)`` and values ``(fl, fr)``,
  not from its flag: finite ends with a sign change (or φ = 0 exactly at the returned x) that are
  no more than ``xtol`` apart or adjacent floats (their midpoint rounds to an end), within the
  ray's step budget.  ``t`` is scipy's ``x`` (the end with the smaller |φ|), inside that bracket.
  Behind a certifying march (``hybrid_chandrupatla``) that closed bracket is the refiner's, of
  φ's signs as computed: the answer then stands once the certified bracket taken from scipy's
  returned ends is within the closing width, else it is verified first, as ``hybrid_secant``'s
  (:meth:`impls.core.rootfind.MarchRefine._verify`).  So behind ``march_chandrupatla`` where φ's
  rounding is modelled (:attr:`impls.core.rootfind.MarchRefine.verifies`): its rows in
  verification take the marchers' verification step in the refinement stage (a sample each), and a
  row whose sample shows the crossing beyond scipy's bracket is refined by scipy again.
* Otherwise: NON_FINITE (t NaN) where scipy reports a non-finite value (status −3) or returns a
  non-finite x; MAX_ITER (t scipy's last x, or the bracket's midpoint where that is NaN) where
  the budget ran out (scipy −2, or more iterations than the ray's ``max_steps`` left: scipy's
  ``maxiter`` is one number, the largest budget left among the rays of the call) or scipy
  stopped on a bracket isobench cannot certify (scipy 0 or −1 on an uncertified bracket).
* ``iterations`` += scipy's ``nit``; ``evals`` += φ evaluations made (scipy's ``nfev`` less the
  two bracket ends, whose φ the march already holds and passes back when scipy asks for them:
  :func:`refine`).

numpy only (``MethodSpec.libs``): scipy's solver runs eagerly on numpy arrays (its array-API
mode is experimental and needs ``SCIPY_ARRAY_API=1``), so the refinement cannot run inside jax's
traced loops, and on torch it would convert at every call.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .rootfind import CONV, IN, MAXI, NONF, UNC, MarchRefine


def refine(a, b, fa, fb, o, d, ev, *, xtol: float, budget):
    """Refine brackets [a, b] (φ(a) = ``fa``, φ(b) = ``fb`` of opposite signs) on rays ``o``, ``d``
    ((m, 3)) with ``scipy.optimize.elementwise.find_root``; ``budget`` (m,) iterations left per ray.

    Returns ``(t, status, nit, evals, (xl, xr, fl, fr))`` per ray as the module docstring states, the
    last scipy's returned bracket and φ at its ends.  φ is evaluated
    through the backend's ``ev(o, d, t, deriv) -> (φ, _, cost)`` on the rays scipy still works on
    (it compacts its arguments, so the ray components travel as ``args``)."""
    from scipy.optimize.elementwise import find_root

    m = a.shape[0]
    O = np.ascontiguousarray(o.T)  # (3, m): the drivers' layout, φ runs on contiguous rows
    D = np.ascontiguousarray(d.T)
    eps = float(np.finfo(a.dtype).eps)
    mag = float(np.max(np.maximum(np.abs(a), np.abs(b)))) if m else 0.0
    calls = {"n": 0, "served": 0, "cost": 1}

    def f(t, ox, oy, oz, dx, dy, dz):
        calls["n"] += 1
        # scipy first evaluates the two bracket ends, whole arrays; the march holds φ there
        if calls["n"] <= 2 and t.shape == a.shape:
            for ends, fends in ((a, fa), (b, fb)):
                if np.array_equal(t, ends):
                    calls["served"] += 1
                    return fends.copy()
        oo, dd = np.stack((ox, oy, oz)), np.stack((dx, dy, dz))
        val, _, cost = ev(oo.T, dd.T, t, False)
        calls["cost"] = cost
        return val

    tol = dict(xatol=max(0.0, xtol - eps * mag), xrtol=eps, fatol=0.0, frtol=0.0)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        res = find_root(f, (a, b), args=(O[0], O[1], O[2], D[0], D[1], D[2]), tolerances=tol,
                        maxiter=int(np.max(budget)) if m else 0)
    xl, xr = (np.asarray(v, a.dtype) for v in res.bracket)
    fl, fr = (np.asarray(v, a.dtype) for v in res.f_bracket)
    x, fx = np.asarray(res.x, a.dtype), np.asarray(res.f_x, a.dtype)
    nit = np.asarray(res.nit, np.int64)
    code = np.asarray(res.status)
    mid = 0.5 * (xl + xr)
    ends_ok = np.isfinite(xl) & np.isfinite(xr) & (xl <= xr)
    sign_change = ((fl > 0) != (fr > 0)) | (fl == 0) | (fr == 0)
    narrow = (xr - xl <= xtol) | (mid <= xl) | (mid >= xr)
    exact = (fx == 0) & np.isfinite(x)
    certified = ends_ok & np.isfinite(x) & (exact | (sign_change & narrow)) & (x >= xl) & (x <= xr)
    within = nit <= budget
    nonf = (code == -3) | ~np.isfinite(x)
    status = np.where(certified & within, CONV, np.where(nonf & ~(certified & within), NONF, MAXI)).astype(np.int32)
    t = np.where(status == NONF, np.nan, np.where(np.isfinite(x), x, mid))
    evals = (np.asarray(res.nfev, np.int64) - calls["served"]) * calls["cost"]
    return t.astype(a.dtype), status, nit, evals, (xl, xr, fl, fr)


@dataclasses.dataclass(frozen=True)
class MarchChandrupatla(MarchRefine):
    """:class:`impls.core.rootfind.MarchRefine` whose refinement stage is one call of scipy's
    ``find_root`` on every bracket the driver passes it (:func:`refine`; the module docstring
    states the contract).  Build it with ``refiner=Bisect()`` (no refiner state is carried)."""

    def step_refine(self, xp, s, o, d, ev):
        if xp is not np:
            raise TypeError("march_chandrupatla refines with scipy.optimize.elementwise.find_root on numpy arrays; "
                            f"the array namespace here is {getattr(xp, '__name__', xp)!r} (numpy backend only)")
        if self.verifies and not self.rule.certifies and np.any(s["vm"]):
            return self._refine_and_verify(s, o, d, ev)
        budget = self.max_steps - s["iterations"]
        fb = s["f"]
        if self.verifies and not self.rule.certifies:
            # φ at b: the march's last sample, or, for a row whose verification resumed refinement
            # beyond its answer ([c, b], MarchRefine._verify), φ(c) is the start side's and φ(b) was
            # not kept: a value of b's side, which scipy takes only for its first interpolation (its
            # bracket moves by the signs it evaluates); no evaluation is counted for it
            fb = np.where((fb > 0) == (s["fa"] > 0), -s["fa"], fb)
        t, status, nit, evals, (xl, xr, fl, fr) = refine(s["a"], s["b"], s["fa"], fb, o, d, ev, xtol=self.xtol,
                                                         budget=budget)
        new = dict(t=t, status=status, iterations=s["iterations"] + nit, evals=s["evals"] + evals)
        if self.verifies:
            # scipy's root lies in a closed bracket; it is an answer once the certified bracket is
            # within the closing width (else it is verified first: MarchRefine._verify)
            ok, verify = self._settled(s, new, status, xl, xr, fl, fr)
            t = new["t"]
        if self.rule.certifies:
            # and the ray's first crossing when the march's frontier reaches it (MarchRefine._certify),
            # else the certification stage samples towards it from the last certified point,
            # bisecting an earlier crossing it finds
            later = ok & (s["u"] + self.rule.min_step < new["a"])
            # a frontier stopped behind the last certified sample (MarchRefine.step_refine): UNCERTIFIED
            unc = later & (s["u"] < s["cp"])
            later = later & ~unc
            status = np.where(unc, UNC, status)
            on = later | verify
            new.update(status=np.where(on, IN, status), cm=later, vm=verify, zl=t, zr=t,
                       phase=np.where(on, len(self.stages) - 1, len(self.stages) - 2).astype(np.int32))
        elif self.verifies:
            # a constant-step march where φ's rounding is modelled: the rows to verify sample in this
            # stage (_refine_and_verify); a root the march's frontier leaves more than a step behind
            # is UNCERTIFIED either way (ConstantStep.late)
            status = np.where(ok & self.rule.late(np, s["g"], new["a"]), UNC, np.where(verify, IN, status))
            new.update(status=status, vm=verify, zl=t, zr=t)
        else:
            # the march's frontier (ConstantStep.late): a root it leaves more than a step behind is
            # not certified the first crossing (scipy's bracket is not returned: its root bounds it)
            new.update(status=np.where((status == CONV) & self.rule.late(np, s["g"], t), UNC, status))
        return {**s, **{k: v.astype(s[k].dtype) if k in s else v for k, v in new.items()}}

    def _settled(self, s, new, status, xl, xr, fl, fr):
        """The certified bracket [A, B] from scipy's returned ends (:meth:`MarchRefine._bracket_sample`:
        its left end has the march's start side) into ``new``, the closed rows whose [A, B] is within
        the closing width settled into it (:meth:`MarchRefine._settle`, ``new``'s bracket the march's
        own before that); returns ``(ok, verify)``: those rows, and the closed rows to verify."""
        with np.errstate(invalid="ignore"):
            lft = self._bracket_sample(np, s, xl, fl, (fl > 0) == (s["fa"] > 0))
            got = self._bracket_sample(np, dict(s, **lft), xr, fr, (fr > 0) == (s["fa"] > 0))
        fin = np.isfinite(xl) & np.isfinite(xr) & np.isfinite(fl) & np.isfinite(fr) & (xl <= xr)
        new.update(A=np.where(fin, got["A"], s["A"]), B=np.where(fin, got["B"], s["B"]))
        closed = status == CONV
        ok = closed & (new["B"] - new["A"] <= self.closing_width(np, new["t"], s["mag"]))
        new.update(a=s["a"], b=s["b"])
        self._settle(np, new, ok)
        return ok, closed & ~ok

    def _refine_and_verify(self, s, o, d, ev):
        """:meth:`step_refine` on a batch holding rows in verification mode: those take
        :meth:`impls.core.rootfind.MarchRefine._refine_verified`'s step (one sample each; a row
        whose sample shows the crossing beyond its bracket leaves verification and is refined by
        scipy again at its next step), the others scipy's refinement; each part on its own rows,
        so that no row evaluates φ for the other's step."""
        vm = s["vm"]
        parts = []
        for rows, step in ((np.flatnonzero(vm), lambda *a: MarchRefine._refine_verified(self, np, *a)),
                           (np.flatnonzero(~vm), lambda *a: self.step_refine(np, *a))):
            if rows.size:
                sub = {k: v[rows] for k, v in s.items()}
                parts.append((rows, step(sub, o[rows], d[rows], ev)))
        # (what both steps write: the stage's state and the status; the refiner's p, fp are neither's)
        keys = set.intersection(*(set(got) for _, got in parts))
        out = {k: np.empty(vm.shape[:1] + parts[0][1][k].shape[1:], parts[0][1][k].dtype) for k in keys}
        for rows, got in parts:
            for k in keys:
                out[k][rows] = got[k]
        return out

