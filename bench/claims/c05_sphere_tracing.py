"""Claim 5: sphere tracing (t ← t + φ, until |φ| ≤ ε) terminates at the first hit for SDFs; what it does
on implicit functions that are not SDFs, with the plain step φ and with the Lipschitz step φ/L
(lecture, "Ray marching: Sphere Tracing"; Hart 1996).

A ray is handled correctly when: it hits and the tracer converged, no iterate went past the first hit
(+1e-9 relative) and it stopped within 1e-3 of that hit (the distance the tolerance allows is far
smaller; 1e-3 only separates "the first hit" from "some other surface"); or it misses and the tracer
did not converge.  A trial (function × step × ray family) holds when every ray is handled correctly
within the step budget.
"""

from __future__ import annotations


import numpy as np

from reference import AlgebraicSphere, Difference, Ellipsoid, Scaled, Sphere, Union

from .adapters import label
from .scenes import AXES, torus
from .figures import figure
from .ledger import LEDGER, Trial
from .tracing import camera_rays, sphere_trace_signed

TOL = 1e-10
R_DOMAIN = 4.0  # every ray starts within |x| ≤ 4, so L = 2·4 bounds |∇(|x|²−1)| where it matters


def _grazing_rays(ks):
    """Rays along −z at impact parameter 1 ± 10^-k from the unit sphere's centre (exact in binary)."""
    b = np.concatenate([1 - 10.0 ** -np.asarray(ks, float), 1 + 10.0 ** -np.asarray(ks, float)])
    o = np.stack([b, np.zeros_like(b), np.full_like(b, 3.0)], -1)
    d = np.tile([0.0, 0.0, -1.0], (b.size, 1))
    return o, d, b


def _cases():
    """(reference scene, display name, step divisor L, label); the Lipschitz steps use the scenes' own
    stated bounds (``info.lipschitz``, valid on |x| ≤ R_DOMAIN)."""
    sph = Sphere()
    alg = AlgebraicSphere(domain_radius=R_DOMAIN)
    ell = Ellipsoid(AXES, domain_radius=R_DOMAIN)
    union = Union(Sphere((-0.4, 0, 0), 0.7), Sphere((0.5, 0.2, 0), 0.6))
    # max(|x|−1.01, 0.99−|x|) = ||x|−1| − 0.01: a thin spherical shell, an exact SDF
    shell = Difference(Sphere(radius=1.01), Sphere(radius=0.99))
    la, le = alg.info.lipschitz, ell.info.lipschitz
    return [
        (sph, label(sph), 1.0, "SDF, step φ"),
        (union, "union of two sphere SDFs (distance bound)", 1.0, "SDF bound, step φ"),
        (shell, "thin shell SDF ||x|−1|−0.01 (difference of spheres)", 1.0, "SDF, step φ"),
        (torus(), label(torus()), 1.0, "SDF, step φ"),
        (Scaled(sph, 0.5), label(Scaled(sph, 0.5)), 1.0, "non-SDF 0.5·SDF, step φ (L=0.5 ≤ 1)"),
        (Scaled(sph, 2.0), label(Scaled(sph, 2.0)), 1.0, "non-SDF 2·SDF, step φ (no Lipschitz step)"),
        (Scaled(sph, 2.0), label(Scaled(sph, 2.0)), Scaled(sph, 2.0).info.lipschitz, "non-SDF 2·SDF, Lipschitz step φ/2"),
        (alg, label(alg), 1.0, "non-SDF |x|²−1, step φ (no Lipschitz step)"),
        (alg, label(alg), la, f"non-SDF |x|²−1, Lipschitz step φ/{la:g}"),
        (ell, label(ell), 1.0, "non-SDF ellipsoid quadric, step φ (no Lipschitz step)"),
        (ell, label(ell), le, f"non-SDF ellipsoid quadric, Lipschitz step φ/{le:g}"),
    ]


def _judge(r, t_ref):
    hit = np.isfinite(t_ref)
    with np.errstate(invalid="ignore"):
        passed = hit & (r.t_furthest > t_ref + 1e-9 * (1 + t_ref))
        good_hit = hit & r.converged & ~passed & (np.abs(r.t - t_ref) <= 1e-3)
    good_miss = ~hit & ~r.converged & ~np.isfinite(r.t)
    return {"rays": int(t_ref.size), "hits": int(hit.sum()), "passed_through": int(passed.sum()),
            "false_hits": int((~hit & r.converged).sum()), "no_termination": int((np.isfinite(r.t) & ~r.converged).sum()),
            "correct": int((good_hit | good_miss).sum())}


_HOW = (f"signed steps from t=0, ε={TOL:g}; pinhole rays on SDFs (sphere, union, thin shell, torus) and "
        "non-SDFs (k·SDF, |x|²−1, ellipsoid quadric) with step φ and φ/L (L valid on |x| ≤ 4); grazing rays at "
        "impact 1±10^-k on the sphere; exact first hits of the reference scenes (quadratic, quartic, CSG interval "
        "algebra); a trial holds if every ray stops at its first hit (or leaves, for a miss) within the budget")


def _part(how: str) -> str:
    """Which part of the compound claim a trial of :func:`_cases` belongs to: SDFs (and distance
    bounds) with step φ; non-SDFs with the Lipschitz step φ/L; non-SDFs with the plain step φ (which is a
    Lipschitz step where L ≤ 1: the class 5c holds on)."""
    if how.startswith("SDF"):
        return "5a"
    return "5c" if ("no Lipschitz step" in how or "step φ (L=" in how) else "5b"


def _tracing(ctx):
    """The trials of claims 5a–5c, computed once per context: (part → trials, key numbers, figure)."""
    n_side = 12 if ctx.quick else 48
    budget = 5000 if ctx.quick else 50_000
    o, d = camera_rays(n_side, eye=(0.3, 0.4, 3.0), fov_deg=50.0)
    trials, key, rows = [], {}, []
    for scene, name, lip, how in _cases():
        t_ref = scene.first_hit(o, d)  # exact: closed-form roots / interval algebra of the reference
        t_ref = np.where(t_ref <= 10.0, t_ref, np.inf)
        r = sphere_trace_signed(scene.value, o, d, lipschitz=lip, tol=TOL, max_steps=budget, t_max=10.0)
        nums = _judge(r, t_ref)
        nums["mean_steps"] = float(r.iterations.mean())
        cond = f"{name}: {how}, camera rays ({budget} steps)"
        classes = ("Lipschitz constant ≤ 1",) if "L=0.5" in how else ("rays that do not graze",)
        trials.append((_part(how), Trial(cond, nums["correct"] == nums["rays"], nums, classes=classes)))
        key[f"{name} [{how}]: correct/rays"] = f"{nums['correct']}/{nums['rays']}"
        key[f"{name} [{how}]: passed through"] = nums["passed_through"]
        rows.append((f"{name[:22]} / {how.split(',')[-1].strip()[:24]}", nums["correct"] / nums["rays"],
                     nums["mean_steps"]))
    # grazing hits and near misses on the exact sphere SDF
    ks = np.arange(2, 13)
    og, dg, b = _grazing_rays(ks)
    sph = Sphere()
    t_ref = sph.first_hit(og, dg)
    r = sphere_trace_signed(sph.value, og, dg, lipschitz=1.0, tol=TOL, max_steps=budget * 4, t_max=10.0)
    nums = _judge(r, t_ref)
    false_at = b[(~np.isfinite(t_ref)) & r.converged]
    nums["false_hit_min_miss_distance"] = float((false_at - 1).min()) if false_at.size else 0.0
    trials.append(("5a", Trial(f"sphere SDF, step φ, grazing rays impact 1±10^-k, k=2..12 (ε={TOL:g}, {budget * 4} "
                               "steps)", nums["correct"] == nums["rays"], nums)))
    key["grazing: correct/rays"] = f"{nums['correct']}/{nums['rays']}"
    key["grazing: false hits (misses closer than ε)"] = nums["false_hits"]
    steps_hit = r.iterations[: ks.size]
    key["grazing: steps for impact 1−10^-k, k=2..12"] = steps_hit.tolist()

    fig, axes = figure(2, 1, 5.2, 4.6)
    names = [x[0] for x in rows]
    axes[0].barh(names, [x[1] for x in rows])
    axes[0].set_xlabel("fraction of camera rays handled correctly")
    axes[0].tick_params(axis="y", labelsize=6)
    axes[1].loglog(10.0 ** -ks, np.maximum(steps_hit, 1), "o-", label="hits (impact 1−10^-k)")
    axes[1].loglog(10.0 ** -ks, np.maximum(r.iterations[ks.size:], 1), "s--", label="near misses (1+10^-k)")
    axes[1].axvline(TOL, color="k", ls=":", label="ε")
    axes[1].set_xlabel("|impact parameter − 1| (length units)")
    axes[1].set_ylabel("sphere-tracing steps")
    axes[1].legend(fontsize=7)
    parts = {p: [t for q, t in trials if q == p] for p in ("5a", "5b", "5c")}
    return parts, key, fig


LEDGER.parts(_tracing, [
    dict(id="5a",
         statement="sphere tracing t ← t + f(x), until |f| ≤ ε, terminates at the first intersection for SDFs",
         equation="slide 'Ray marching: Sphere Tracing'",
         how_checked=_HOW,
         scope="exact SDFs and distance bounds (|φ| ≤ distance), camera and grazing rays, a finite step budget; "
         "named class: rays that do not graze the surface (a near miss at distance δ needs ~√(1/δ) steps)"),
    dict(id="5b",
         statement="on non-SDF implicit functions sphere tracing with the Lipschitz step φ/L terminates at the first "
         "intersection",
         equation="slide 'Ray marching: Sphere Tracing' (the question it raises)",
         how_checked=_HOW,
         scope="any implicit function with a valid Lipschitz bound L on the traced region"),
    dict(id="5c",
         statement="on non-SDF implicit functions sphere tracing with the plain step φ (no Lipschitz bound) terminates "
         "at the first intersection",
         equation="slide 'Ray marching: Sphere Tracing' (the question it raises)",
         how_checked=_HOW,
         scope="any implicit function, step φ; named class: functions whose Lipschitz constant is ≤ 1 (then step φ "
         "is a Lipschitz step)"),
])
