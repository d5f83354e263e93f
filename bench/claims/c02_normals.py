"""Claim 2: normal ∇φ/|∇φ|, closest point x − φ(x)N(x), and |∇φ| = 1 for SDFs
(lecture, "Properties - SDF" and "Properties - Normal").

Gradients are central differences (h = 1e-6, error ≈ h²|φ'''| + ε|φ|/h ≲ 1e-9), so every
tolerance below (1e-6) is three orders above the measurement error.  The shapes are the reference
scenes; the exact normals and closest points come from each surface's *parametrisation*
(:func:`geometric_normal`, :func:`geometric_closest`), not from ∇φ: the reference's own
``normal_exact`` and ``closest_point_exact`` are defined as ∇φ/|∇φ| and x − φ∇φ — the very formulas
under test — so they cannot serve as the truth here.
"""

from __future__ import annotations

import numpy as np

from reference import AlgebraicSphere, Box, CallableField, Ellipsoid, Scaled, Sphere
from reference.arrays import unit

from .adapters import label
from .figures import figure
from .ledger import LEDGER, Evidence, Trial
from .scenes import AXES, geometric_closest, geometric_normal, surface_points, torus
from .stats import central_gradient

H = 1e-6
TOL = 1e-6


def _normal_cases():
    sph, alg = Sphere(), AlgebraicSphere()
    sq = CallableField(lambda x, xp: alg.value(x, xp) ** 2, name="squared algebraic sphere")
    return [("sphere", label(sph), sph), ("sphere", label(alg), alg), ("sphere", label(Scaled(sph, 2.0)), Scaled(sph, 2.0)),
            ("torus", label(torus()), torus()), ("ellipsoid", label(Ellipsoid(AXES)), Ellipsoid(AXES)),
            ("sphere", "squared algebraic sphere (|x|²−1)²", sq)]


@LEDGER.claim(
    "2a",
    statement="the normal of the surface φ = 0 is n(x) = ∇φ(x)/‖∇φ(x)‖",
    equation="slide 'Properties - Normal', eq. (1)",
    how_checked="surface points from each shape's parametrisation; ∇φ by central differences (h=1e-6); "
    "exact normal from the parametrisation (cross product of tangents / radial direction); a trial (shape) "
    "holds if the largest angle between them is ≤ 1e-6 rad",
    scope="any implicit φ whose zero set is a regular level set (∇φ ≠ 0 on it, the premise of eq. (1)); "
    "a trial is outside the scope when min |∇φ| on the surface is below 1e-6 (∇φ/|∇φ| is then 0/0)",
)
def check_normal(ctx):
    rng = np.random.default_rng(ctx.seed)
    n = 2000 if ctx.quick else 50_000
    trials, key, curves = [], {}, []
    for fam, name, shape in _normal_cases():
        x = surface_points(fam, n, rng)
        g = central_gradient(shape.value, x, H)
        gn = np.linalg.norm(g, axis=-1)
        ex = geometric_normal(fam, x)
        # angle by atan2(|a×b|, a·b): accurate for tiny angles, unlike arccos (≈1e-8 floor)
        ang = np.arctan2(np.linalg.norm(np.cross(g, ex), axis=-1), np.sum(g * ex, -1))
        worst = float(ang.max())
        cond = f"{name} (min |∇φ| on surface {gn.min():.2g})"
        trials.append(Trial(cond, worst <= TOL, {"max_angle_rad": worst}, in_scope=bool(gn.min() > 1e-6)))
        key[f"{name}: max angle"] = worst
        curves.append((name, np.sort(ang)))
    fig, (ax,) = figure(1, 1, 6.5, 4)
    for name, a in curves:
        ax.semilogy(np.linspace(0, 1, a.size), np.maximum(a, 1e-17), label=name)
    ax.axhline(TOL, color="k", ls=":", label="criterion 1e-6 rad")
    ax.set_xlabel("fraction of surface points (sorted)")
    ax.set_ylabel("angle(∇φ/|∇φ|, exact normal) (rad)")
    ax.legend(fontsize=7)
    return Evidence(trials, key, fig)


def _shell_points(fam: str, n: int, rng, width=0.3):
    """Points within ``width`` of the surface along the exact normal (away from the medial axis)."""
    base = surface_points(fam, n, rng)
    return base + rng.uniform(-width, width, n)[:, None] * geometric_normal(fam, base)


@LEDGER.claim(
    "2b",
    statement="the closest surface point is x_s = x − φ(x) N(x) ('not strictly'; for which functions?)",
    equation="slide 'Properties - SDF'",
    how_checked="points within 0.3 of the surface (off the medial axis); N = ∇φ/|∇φ| by central differences; "
    "a trial (shape) holds if max |x_s − exact closest point| ≤ 1e-6",
    scope="any implicit φ (the slide asks for which functions it holds), points near the surface off the "
    "medial axis; named class: exact SDFs",
)
def check_closest(ctx):
    rng = np.random.default_rng(ctx.seed + 1)
    n = 2000 if ctx.quick else 50_000
    sph = Sphere()
    cases = [("sphere", sph), ("torus", torus()), ("sphere", AlgebraicSphere()), ("sphere", Scaled(sph, 2.0)),
             ("sphere", Scaled(sph, 0.5))]
    trials, key, bars = [], {}, []
    for fam, shape in cases:
        x = _shell_points(fam, n, rng)
        N = unit(central_gradient(shape.value, x, H))
        xs = x - shape.value(x)[:, None] * N
        err = float(np.max(np.linalg.norm(xs - geometric_closest(fam, x), axis=-1)))
        name = label(shape)
        trials.append(Trial(name + (" (exact SDF)" if shape.info.exact_sdf else " (not an SDF)"), err <= TOL,
                            {"max_err": err}, classes=("exact SDFs",) if shape.info.exact_sdf else ()))
        key[f"{name}: max |x_s − closest|"] = err
        bars.append((name, err))
    fig, (ax,) = figure(1, 1, 6.5, 4)
    ax.barh([b[0] for b in bars], [max(b[1], 1e-17) for b in bars])
    ax.set_xscale("log")
    ax.axvline(TOL, color="k", ls=":", label="criterion 1e-6")
    ax.set_xlabel("max |x − φ(x)N(x) − exact closest point| (length units)")
    ax.legend(fontsize=7)
    return Evidence(trials, key, fig)


@LEDGER.claim(
    "2c",
    statement="signed distance functions satisfy ‖∇φ(x)‖ = 1",
    equation="slide 'Properties - SDF'",
    how_checked="exact SDFs (sphere, torus, box) at random points of [−2,2]³; ∇φ by central differences "
    "with h and 2h, points where the two disagree by > 1e-6 are counted as on a kink (the medial axis, "
    "where φ is not differentiable) and excluded; a trial holds if max ||∇φ|−1| ≤ 1e-6 elsewhere and kinks "
    "are ≤ 1% of the points",
    scope="exact SDFs, wherever φ is differentiable (off the medial axis, a set of measure zero)",
)
def check_unit_gradient(ctx):
    rng = np.random.default_rng(ctx.seed + 2)
    n = 20_000 if ctx.quick else 400_000
    x = rng.uniform(-2, 2, (n, 3))
    trials, key, hist = [], {}, []
    for shape in (Sphere(), torus(), Box((0.8, 0.5, 0.3))):
        g1 = central_gradient(shape.value, x, H)
        g2 = central_gradient(shape.value, x, 2 * H)
        kink = np.max(np.abs(g1 - g2), axis=-1) > 1e-6
        dev = np.abs(np.linalg.norm(g1, axis=-1) - 1)[~kink]
        worst, frac = float(dev.max()), float(kink.mean())
        name = label(shape)
        trials.append(Trial(name, worst <= TOL and frac <= 0.01, {"max_dev": worst, "kink_fraction": frac}))
        key[f"{name}: max ||∇φ|−1|"] = worst
        key[f"{name}: kink fraction"] = frac
        hist.append((name, dev))
    fig, (ax,) = figure(1, 1, 6.5, 4)
    for name, dev in hist:
        ax.hist(np.log10(np.maximum(dev, 1e-17)), bins=60, histtype="step", label=name)
    ax.set_xlabel("log10 ||∇φ| − 1| (dimensionless)")
    ax.set_ylabel("points")
    ax.legend(fontsize=7)
    return Evidence(trials, key, fig)
