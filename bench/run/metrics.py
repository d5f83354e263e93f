"""Accuracy of any method against the reference, generic over method families.

(The reference answers come from the case — ``Case.exact_*`` of :mod:`reference.cases`, cached
on the case — and the rendering integral, with its time limit and disk cache, from
:mod:`bench.run.references`; this module turns them into errors.)

Every method returns a :class:`impls.protocol.RayResult`; what it is checked against depends on
its family (:attr:`impls.methods.MethodSpec.family`) and on the per-ray outputs it declares
(:attr:`MethodSpec.outputs`).  Each checked *quantity* becomes one long-format result row:

=====================  ================================  =========================================
output                 quantity (unit)                   reference
=====================  ================================  =========================================
``t`` (family root)    ``depth`` (scene units)           exact first hit t* (``case.exact_t``)
``normal``             ``normal_angle`` (rad)            exact unit normal N(x*) at x* = o + t* d
``curvature_sum``,     ``<name>`` (1/scene units)        κ1 + κ2 (the lecture's "mean curvature")
``curvature_divergence``
``curvature_laplacian``  ``curvature_laplacian``         κ1 + κ2, only for exact SDFs (|∇φ| = 1
                                                         makes Δφ = ∇·(∇φ/|∇φ|) = κ1 + κ2;
                                                         elsewhere Δφ is a different quantity)
``mean_curvature``     ``mean_curvature``                (κ1 + κ2)/2
``gaussian_curvature`` ``gaussian_curvature`` (1/u²)     κ1 κ2
``dt_dtheta``          ``dt_dtheta`` (units per param)   exact dt/dθ (n, P) of the hit depth
``color``              ``color_vs_integral``             C = ∫ T σ ρ dt, ``render_exact`` with the
                                                         method's density model and sharpness
``color``              ``color_vs_surface``              the surface-rendered image: ρ(x*) at the
                                                         exact hit, the background 0 where the
                                                         exact answer misses
=====================  ================================  =========================================

Conventions (the reference's, ``reference/scene.py``): κ > 0 where the surface bends away
from its outward normal (a sphere of radius r has κ1 = κ2 = 1/r, Δφ = 2/r).

Errors per ray: e = |got − exact| for scalars, the Euclidean norm of the difference for
vectors (dt/dθ, colour), and for normals the larger of the angle atan2(|n × n*|, n·n*) (stable at
0 and π) and | |n| − 1 | (a normal is a unit vector: the angle alone scores n = 0 or 3·n* as exact).
Columns per quantity: ``error_max``, ``error_p99``, ``error_median`` (absolute),
``error_rel_max`` = max e/|exact| (|exact| floored at the dtype's smallest normal),
``error_ulps_max`` = max e/ulp(exact) with ulp the spacing of |exact| in the run's dtype (ulp(1)
where exact = 0), and ``error_max_eps`` = max e/(eps·max(|exact|, 1)).

Root finders also report ``error_iterate_median``: the median over hitting rays of |t − t*| for the
returned iterate whatever its status (the convergence plot's y: a budget that ran out still
leaves an iterate whose error shrinks with the budget).

Rays the reference flags (``case.judged_mask`` False: no certified answer, e.g. a declared
Lipschitz bound seen to be false, or a near-tangent ray float64 cannot call a hit or a miss;
:attr:`reference.cases.Case.exact_t_error_bounds`) are *not judged*: left out of the depth errors,
of ``n_false_hit``/``n_false_miss`` and of ``color_vs_surface``, counted in ``n_not_judged``
(``reference_error_bound``: the largest depth bound of the judged rays).  Such a row was not fully
checked: :func:`bench.report.summary.which_to_pick` never picks it, :mod:`bench.studies.stability`
counts its rays as not judged, :mod:`bench.report.compare` calls it not comparable when the count changed.

Honesty rules: a root finder's false hit or false miss has e = inf (a max error cannot hide a
wrong answer), and so has a non-finite output on a ray whose status says ``CONVERGED`` (a silent
NaN); rays a method *declined* with a failure status (e.g. ``ILL_CONDITIONED`` for grazing dt/dθ)
are left out of the error and counted in ``n_declined`` and the status histogram; a root finder's
``n_declined`` also counts a miss it did not certify (UNCERTIFIED, MAX_ITER: e = 0, no answer), a
renderer's every declined ray.  ``which_to_pick`` picks such a row only under ``FLAGGED_SHARE``.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable

import numpy as np

from impls.protocol import RayResult, Status

from reference.cases import NoExactAnswer

from .references import NotApplicable, color_field, density_model, exact_color

#: what a quantity that cannot be checked raises: the case has no such exact answer, or bench
#: cannot obtain it (a skipped row with the message as its reason)
_SKIP = (NotApplicable, NoExactAnswer)


@dataclasses.dataclass(frozen=True)
class Quantity:
    """One checked quantity: per-ray errors against an exact answer."""

    name: str
    unit: str
    got: np.ndarray  # (n,) or (n, k)
    exact: np.ndarray  # same shape
    rays: np.ndarray  # bool (n,): rays the error is taken over
    angle: bool = False


def _ulp(x: np.ndarray, dtype: str) -> np.ndarray:
    a = np.abs(x).astype(dtype)
    a = np.where(a == 0, np.asarray(1, dtype), a)
    return np.spacing(a).astype(np.float64)


def finite_rows(a: np.ndarray) -> np.ndarray:
    """Per row (ray): every entry finite.  Works for (n,), (n, k) and n = 0."""
    a = np.asarray(a)
    return np.isfinite(a) if a.ndim == 1 else np.all(np.isfinite(a.reshape(a.shape[0], -1 if a.size else 1)), axis=1)


def _per_ray(q: Quantity) -> tuple[np.ndarray, np.ndarray]:
    """(errors, |exact|) over ``q.rays`` where the exact answer is finite (it is NaN at misses
    and, for curvature, on edges); a non-finite output there → inf."""
    rays = q.rays & finite_rows(q.exact)
    got, ex = q.got[rays], q.exact[rays]
    if q.angle:
        # (the angle alone scores n = 0 or 3·n* as exact; a normal is a unit vector: impls.protocol)
        cross = np.linalg.norm(np.cross(got, ex), axis=-1)
        dot = np.einsum("ij,ij->i", got, ex)
        e = np.maximum(np.arctan2(cross, dot), np.abs(np.linalg.norm(got, axis=-1) - 1.0))
        mag = np.ones(e.shape)
    elif got.ndim == 2:
        e = np.linalg.norm(got - ex, axis=1)
        mag = np.linalg.norm(ex, axis=1)
    else:
        e = np.abs(got - ex)
        mag = np.abs(ex)
    e = np.where(finite_rows(got), e, np.inf)
    return e, mag


def error_stats(e: np.ndarray, mag: np.ndarray, dtype: str) -> dict:
    """Summary columns of per-ray errors ``e`` against answers of magnitude ``mag``."""
    if e.size == 0:
        nan = float("nan")
        return {"error_max": nan, "error_p99": nan, "error_median": nan, "error_max_finite": nan,
                "error_rel_max": nan, "error_ulps_max": nan, "error_max_eps": nan, "n_checked": 0}
    eps = float(np.finfo(dtype).eps)
    tiny = float(np.finfo(dtype).tiny)
    finite = e[np.isfinite(e)]
    with np.errstate(invalid="ignore", divide="ignore"):
        rel = np.where(e == 0, 0.0, e / np.maximum(mag, tiny))
        ulps = np.where(e == 0, 0.0, e / _ulp(mag, dtype))
        in_eps = np.where(e == 0, 0.0, e / (eps * np.maximum(mag, 1.0)))
    return {
        "error_max": float(e.max()),
        "error_p99": float(np.percentile(e, 99, method="inverted_cdf")),
        "error_median": float(np.percentile(e, 50, method="inverted_cdf")),
        "error_max_finite": float(finite.max()) if finite.size else float("nan"),
        "error_rel_max": float(rel.max()),
        "error_ulps_max": float(ulps.max()),
        "error_max_eps": float(in_eps.max()),
        "n_checked": int(e.size),
    }


def work_stats(res: RayResult) -> dict:
    """Evaluations per ray (mean, p99, max) and the largest iteration count."""
    ev = np.asarray(res.evals)
    return {
        "evals_per_ray": float(ev.mean()) if ev.size else 0.0,
        "evals_p99": float(np.percentile(ev, 99)) if ev.size else 0.0,
        "evals_max": int(ev.max()) if ev.size else 0,
        "iterations_max": int(np.max(res.iterations)) if ev.size else 0,
    }


# -- per-family quantities --------------------------------------------------------------------


def depth_errors(res: RayResult, exact_t: np.ndarray) -> np.ndarray:
    """|t − t*| per ray; 0 where both call a miss, inf for a false hit or false miss."""
    exact_hit = np.isfinite(exact_t)
    got_hit = (res.status == Status.CONVERGED) & np.isfinite(res.t)
    e = np.full(exact_t.shape, np.inf)
    both = exact_hit & got_hit
    e[both] = np.abs(res.t[both] - exact_t[both])
    e[~exact_hit & ~got_hit] = 0.0
    return e


def judged_rays(case) -> np.ndarray:
    """The rays a method's depth, hit or miss is judged on: those whose reference answer is
    certified (``case.judged_mask``: a finite per-ray depth bound and a depth that is not NaN;
    :attr:`reference.cases.Case.judged_mask`).  A case without that mask (a stand-in in a test)
    judges every ray whose depth is not NaN."""
    exact_t = np.asarray(case.exact_t, np.float64)
    mask = getattr(case, "judged_mask", None)
    return ~np.isnan(exact_t) if mask is None else np.asarray(mask, bool) & ~np.isnan(exact_t)


def root_metrics(res: RayResult, case, dtype: str, knobs: dict, cache: dict) -> list[dict]:
    exact_t = np.asarray(case.exact_t, np.float64)
    judged = judged_rays(case)
    e = depth_errors(res, exact_t)[judged]
    exact_hit = np.isfinite(exact_t)
    got_hit, declined = res.status == Status.CONVERGED, _declined(res)
    mag = np.where(exact_hit, np.abs(np.where(exact_hit, exact_t, 0.0)), 0.0)[judged]
    # The iterate's error whatever its status (a budget that ran out leaves a finite last
    # iterate): what a convergence plot in the step budget needs; the max error above stays inf.
    jh = exact_hit & judged
    it = np.abs(np.asarray(res.t, np.float64)[jh] - exact_t[jh])
    it = it[np.isfinite(it)]
    # Rays the reference flags (no certified answer: a false Lipschitz bound, a near-tangent ray)
    # are left out of the errors and of the false hit/miss counts, and counted in n_not_judged:
    # a method's answer there can be neither right nor wrong (bench.report.summary never picks such a row).
    # n_false_miss counts every judged ray that hits but is not CONVERGED; of those, the ones the
    # method declined with a failure status (MAX_ITER, NON_FINITE, LIPSCHITZ_VIOLATED…) are flagged,
    # not silent: n_miss_declined lets a reader (bench.studies.stability) tell them apart from reported
    # MISSes.  n_converged_nonfinite: CONVERGED with a non-finite t, a silent NaN (on any ray).
    bounds = getattr(case, "exact_t_error_bounds", None)
    if bounds is not None:
        ref_bound = float(np.max(np.asarray(bounds, np.float64)[judged], initial=0.0))
    else:
        ref_bound = float(getattr(case, "exact_t_error_bound", 0.0) or 0.0)
    row = {"quantity": "depth", "unit": "scene units", **error_stats(e, mag, dtype),
           "n_false_hit": int(np.sum(got_hit & ~exact_hit & judged)), "n_false_miss": int(np.sum(~got_hit & jh)),
           "n_miss_declined": int(np.sum(declined & jh)), "n_declined": int(np.sum(declined & judged)),
           "n_converged_nonfinite": int(np.sum(got_hit & ~np.isfinite(np.asarray(res.t, np.float64)))),
           "n_not_judged": int(np.sum(~judged)),
           "error_iterate_median": float(np.median(it)) if it.size else float("nan"),
           "reference_error_bound": ref_bound}
    return [row]


def _declined(res: RayResult) -> np.ndarray:
    return (res.status != Status.CONVERGED) & (res.status != Status.MISS)


_CURVATURE_OUTPUTS: dict[str, Callable[[np.ndarray, np.ndarray], np.ndarray]] = {
    "curvature_sum": lambda k1, k2: k1 + k2,
    "curvature_divergence": lambda k1, k2: k1 + k2,
    "curvature_laplacian": lambda k1, k2: k1 + k2,
    "mean_curvature": lambda k1, k2: 0.5 * (k1 + k2),
    "gaussian_curvature": lambda k1, k2: k1 * k2,
}


def _pointwise_quantities(res: RayResult, case, outputs: tuple[str, ...]) -> tuple[list[Quantity], list[dict]]:
    """Quantities of a method evaluated at the exact hits (gradient, param_grad families); the
    exact answers are the case's (cached on it)."""
    rays = case.hit_mask & ~_declined(res)
    qs: list[Quantity] = []
    notes: list[dict] = []
    for name in outputs:
        if name not in res.outputs:
            raise ValueError(f"method declared output {name!r} but returned only {sorted(res.outputs)}")
        got = np.asarray(res.outputs[name], np.float64)
        try:
            if name == "normal":
                qs.append(Quantity("normal_angle", "rad", got, case.exact_normals, rays, angle=True))
            elif name in _CURVATURE_OUTPUTS:
                info = case.scene.info
                if name == "curvature_laplacian" and not info.exact_sdf:
                    raise NotApplicable("Δφ equals κ1+κ2 only for exact SDFs (|∇φ| = 1); this scene is not one")
                k1, k2 = case.exact_curvatures
                qs.append(Quantity(name, "1/scene units" if name != "gaussian_curvature" else "1/scene units²",
                                   got, _CURVATURE_OUTPUTS[name](k1, k2), rays))
            elif name == "dt_dtheta":
                ex = case.exact_dt_dtheta
                if got.shape != ex.shape:
                    raise ValueError(f"dt_dtheta has shape {got.shape}, the reference {ex.shape}")
                qs.append(Quantity(name, "scene units per parameter unit", got, ex, rays))
            elif getattr(case, "exact_" + name, None) is not None:  # a reference answer named after the output
                ex = np.asarray(getattr(case, "exact_" + name), np.float64)
                if got.shape != ex.shape:
                    raise ValueError(f"{name} has shape {got.shape}, case.exact_{name} {ex.shape}")
                qs.append(Quantity(name, "", got, ex, rays))
            else:
                notes.append({"quantity": name, "skip": f"no reference for output {name!r} "
                                                        f"(bench.run.metrics knows none; case.exact_{name} does not exist)"})
        except _SKIP as exc:
            notes.append({"quantity": "normal_angle" if name == "normal" else name, "skip": str(exc)})
    return qs, notes


def pointwise_metrics(res: RayResult, case, dtype: str, knobs: dict, cache: dict, outputs=()) -> list[dict]:
    qs, notes = _pointwise_quantities(res, case, outputs)
    n_declined = int(np.sum(_declined(res) & case.hit_mask))
    rows = []
    for q in qs:
        if q.got.shape[0] != case.n_rays:
            raise ValueError(f"output for {q.name} has {q.got.shape[0]} rows, expected {case.n_rays}")
        e, mag = _per_ray(q)
        rows.append({"quantity": q.name, "unit": q.unit, **error_stats(e, mag, dtype), "n_declined": n_declined})
    return rows + notes


def render_metrics(res: RayResult, case, dtype: str, knobs: dict, cache: dict, spec) -> list[dict]:
    """``color_vs_integral`` (against the continuous rendering integral of the same density, on
    the rays it is computed for: :func:`bench.run.references.reference_rays`) and
    ``color_vs_surface`` (against the surface-rendered image: ρ(x*) where the exact answer hits,
    the background 0 where it misses; the limit volume rendering is meant to approach).  The
    misses count: a renderer that paints them (a volume renderer's halo beside a silhouette, a
    surface renderer's colour on a ray it wrongly calls a hit) is as far from the surface image
    as one that misses a hit, and a case whose every ray misses is judged, not 'none reached'."""
    if "color" not in res.outputs:
        raise ValueError(f"render method returned no 'color' output (outputs: {sorted(res.outputs)})")
    got = np.asarray(res.outputs["color"], np.float64)
    got = got.reshape(case.n_rays, -1) if got.size else got.reshape(case.n_rays, 3)
    rows: list[dict] = []
    everywhere = ~_declined(res)
    refs = (("color_vs_integral", lambda: exact_color(case, spec, knobs, cache), everywhere),
            ("color_vs_surface", lambda: (np.where(case.hit_mask[:, None], case.exact_surface_colors, 0.0), 0.0),
             everywhere & judged_rays(case)))
    for name, exact_fn, rays in refs:
        try:
            ex, bound = exact_fn()
        except _SKIP as exc:
            rows.append({"quantity": name, "skip": str(exc)})
            continue
        if ex.shape != got.shape:
            raise ValueError(f"color has shape {got.shape}, the reference {ex.shape}")
        if name == "color_vs_integral":
            rays = rays & np.all(np.isfinite(ex), axis=1)  # the rays the integral was computed on
        e, mag = _per_ray(Quantity(name, "colour units", got, ex, rays))
        # ρ(x*) is judged where the hit is: not on the rays the reference flags (counted, as root rows do,
        # so that a case whose every hit is flagged reads 'not judged' rather than 'none reached')
        judged = {"n_not_judged": int(np.sum(~judged_rays(case)))} if name == "color_vs_surface" else {}
        rows.append({"quantity": name, "unit": "colour units", **error_stats(e, mag, dtype), **judged,
                     "n_declined": int(np.sum(~everywhere)),
                     "reference_error_bound": bound,
                     "reference_s": cache.pop(("reference_s", case.id, density_model(spec, knobs),
                                               float(knobs.get("sharpness", 0) or 0)), 0.0)})
    return rows


#: family → metric function ``(res, case, dtype, knobs, cache, spec) -> list of row dicts``;
#: a row with a ``skip`` key records a quantity that could not be checked, and why.
FAMILY_METRICS: dict[str, Callable[..., list[dict]]] = {
    "root": lambda res, case, dtype, knobs, cache, spec: root_metrics(res, case, dtype, knobs, cache),
    "gradient": lambda res, case, dtype, knobs, cache, spec: pointwise_metrics(res, case, dtype, knobs, cache,
                                                                               tuple(spec.outputs)),
    "param_grad": lambda res, case, dtype, knobs, cache, spec: pointwise_metrics(res, case, dtype, knobs, cache,
                                                                                 tuple(spec.outputs)),
    "render": render_metrics,
}

#: the main quantity of each family (the one a skipped/failed row is filed under)
PRIMARY_QUANTITY = {"root": "depth", "gradient": "normal_angle", "param_grad": "dt_dtheta", "render": "color_vs_integral"}


def primary_quantity(spec) -> str:
    if spec.family == "gradient" and spec.outputs and "normal" not in spec.outputs:
        return spec.outputs[0]
    return PRIMARY_QUANTITY.get(spec.family, "")


#: output → (case attribute, SceneInfo flag) of its reference answer
_INFO_FLAG = {"normal": ("exact_normals", "exact_normals"), "dt_dtheta": ("exact_dt_dtheta", "exact_hit_param_grad")}
_INFO_FLAG.update({name: ("exact_curvatures", "exact_curvature") for name in _CURVATURE_OUTPUTS})


def _known_absent(case, output: str) -> bool:
    """The scene states it has no exact answer for ``output`` (the flag the reference's
    ``Case.exact_*`` answers require)."""
    if output not in _INFO_FLAG:
        return False
    attr, flag = _INFO_FLAG[output]
    return not getattr(case.scene.info, flag, True)


def family_skip_reason(spec, case) -> str | None:
    """Why a method's family cannot be checked on ``case`` at all (before running it)."""
    if spec.family not in FAMILY_METRICS:
        return f"no accuracy metric for method family {spec.family!r} (known: {sorted(FAMILY_METRICS)})"
    try:
        exact_t = case.exact_t
    except NotImplementedError as exc:
        return f"{case.id} has no exact hits: {exc}"
    if getattr(spec, "finite_range", False) and not math.isfinite(float(case.t_max)):
        return (f"{spec.name} samples the whole interval [t_min, t_max] and {case.id} has t_max = inf "
                "(give the case a finite t_max to render it)")
    if spec.needs_t_hit and not np.isfinite(np.asarray(exact_t)).any():
        return f"{spec.name} evaluates at exact hits and no ray of {case.id} hits"
    if spec.family in ("gradient", "param_grad") and spec.outputs:
        user_field = getattr(case.scene, "kind", None) == "callable"
        if spec.family == "param_grad" and user_field and getattr(case.scene, "params", None) is None:
            return (f"{case.id}'s field has no parameters θ to differentiate its hits by (a user's field takes them "
                    "as CallableField(fn, ..., params=θ), called fn(x, xp, theta))")
        # nothing runs that cannot be checked: every output needs an answer the scene lacks
        missing = [o for o in spec.outputs if _known_absent(case, o)]
        if len(missing) == len(spec.outputs):
            return (f"{case.id} has no exact answer for {', '.join(missing)} "
                    f"(scene states {', '.join(sorted({_INFO_FLAG[o][1] + '=False' for o in missing}))})")
    if spec.family == "render":
        try:
            color_field(case)
        except NotApplicable as exc:
            return f"no colour reference: {exc}"
    return None


def measure_accuracy(spec, res: RayResult, case, dtype: str, knobs: dict, cache: dict) -> list[dict]:
    """All quantity rows for one method result (see the module docstring)."""
    fn = FAMILY_METRICS[spec.family]
    rows = fn(res, case, dtype, knobs, cache, spec)
    work = work_stats(res)
    return [{**r, **work} if "skip" not in r else r for r in rows]


__all__ = ["FAMILY_METRICS", "NotApplicable", "Quantity", "depth_errors", "error_stats", "family_skip_reason",
           "judged_rays", "measure_accuracy", "primary_quantity", "work_stats"]
