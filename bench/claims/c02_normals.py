"""Claim 2: normal ∇φ/|∇φ|, closest point x − φ(x)N(x), and |∇φ| = 1 for SDFs
(lecture, "Properties - SDF" and "Properties - Normal").

Gradients are central differences (h = 1e-6, error ≈ h²|φ'''| + ε|φ|/h ≲ 1e-9), so every
tolerance below (1e-6) is three orders above the measurement error; the exact normals and closest
points come from the shapes' own geometry (``adapters.Shape``), not from ∇φ.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from . import adapters
from .figures import figure
from .ledger import LEDGER, Evidence, Trial
from .stats import central_gradient

H = 1e-6
TOL = 1e-6


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _surface_points(shape_name: str, n: int, rng):
    """Points on the zero set of the named family, from a parametrisation (not from φ)."""
    u = rng.uniform(0, 2 * np.pi, n)
    v = rng.uniform(0.15, np.pi - 0.15, n)  # keep away from the poles of the parametrisation
    if shape_name == "torus":
        R, r = 1.0, 0.4
        return np.stack([(R + r * np.cos(v * 2)) * np.cos(u), (R + r * np.cos(v * 2)) * np.sin(u), r * np.sin(v * 2)], -1)
    if shape_name == "ellipsoid":
        a = (1.0, 0.7, 0.5)
        return np.stack([a[0] * np.cos(u) * np.sin(v), a[1] * np.sin(u) * np.sin(v), a[2] * np.cos(v)], -1)
    return np.stack([np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v)], -1)  # unit sphere


def _normal_cases():
    sph = adapters.sphere_shape()
    alg = adapters.algebraic_sphere_shape()
    sq = dataclasses.replace(alg, name="squared algebraic sphere (|x|²−1)²", f=lambda x: alg.f(x) ** 2)
    return [("sphere", sph), ("sphere", alg), ("sphere", adapters.scaled_shape(sph, 2.0)),
            ("torus", adapters.torus_shape()), ("ellipsoid", adapters.ellipsoid_shape()), ("sphere", sq)]


@LEDGER.claim(
    "2a",
    statement="the normal of the surface φ = 0 is n(x) = ∇φ(x)/‖∇φ(x)‖",
    equation="slide 'Properties - Normal', eq. (1)",
    how_checked="surface points from each shape's parametrisation; ∇φ by central differences (h=1e-6); "
    "exact normal from the parametrisation (cross product of tangents / radial direction); a trial (shape) "
    "holds if the largest angle between them is ≤ 1e-6 rad",
)
def check_normal(ctx):
    rng = np.random.default_rng(ctx.seed)
    n = 2000 if ctx.quick else 50_000
    trials, key, curves = [], {}, []
    for fam, shape in _normal_cases():
        x = _surface_points(fam, n, rng)
        g = central_gradient(shape.f, x, H)
        gn = np.linalg.norm(g, axis=-1)
        ex = shape.normal(x)
        # angle by atan2(|a×b|, a·b): accurate for tiny angles, unlike arccos (≈1e-8 floor)
        ang = np.arctan2(np.linalg.norm(np.cross(g, ex), axis=-1), np.sum(g * ex, -1))
        worst = float(ang.max())
        cond = f"{shape.name} (min |∇φ| on surface {gn.min():.2g})"
        trials.append(Trial(cond, worst <= TOL, {"max_angle_rad": worst}))
        key[f"{shape.name}: max angle"] = worst
        curves.append((shape.name, np.sort(ang)))
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
    base = _surface_points(fam, n, rng)
    shape = adapters.torus_shape() if fam == "torus" else adapters.sphere_shape()
    return base + rng.uniform(-width, width, n)[:, None] * shape.normal(base)


@LEDGER.claim(
    "2b",
    statement="the closest surface point is x_s = x − φ(x) N(x) ('not strictly'; for which functions?)",
    equation="slide 'Properties - SDF'",
    how_checked="points within 0.3 of the surface (off the medial axis); N = ∇φ/|∇φ| by central differences; "
    "a trial (shape) holds if max |x_s − exact closest point| ≤ 1e-6",
)
def check_closest(ctx):
    rng = np.random.default_rng(ctx.seed + 1)
    n = 2000 if ctx.quick else 50_000
    sph = adapters.sphere_shape()
    cases = [("sphere", sph), ("torus", adapters.torus_shape()), ("sphere", adapters.algebraic_sphere_shape()),
             ("sphere", adapters.scaled_shape(sph, 2.0)), ("sphere", adapters.scaled_shape(sph, 0.5))]
    trials, key, bars = [], {}, []
    for fam, shape in cases:
        x = _shell_points(fam, n, rng)
        N = _unit(central_gradient(shape.f, x, H))
        xs = x - shape.f(x)[:, None] * N
        truth = (adapters.torus_shape() if fam == "torus" else sph).closest(x)
        err = float(np.max(np.linalg.norm(xs - truth, axis=-1)))
        trials.append(Trial(f"{shape.name}" + (" (exact SDF)" if shape.exact_sdf else " (not an SDF)"), err <= TOL,
                            {"max_err": err}))
        key[f"{shape.name}: max |x_s − closest|"] = err
        bars.append((shape.name, err))
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
)
def check_unit_gradient(ctx):
    rng = np.random.default_rng(ctx.seed + 2)
    n = 20_000 if ctx.quick else 400_000
    x = rng.uniform(-2, 2, (n, 3))
    trials, key, hist = [], {}, []
    for shape in (adapters.sphere_shape(), adapters.torus_shape(), adapters.box_shape()):
        g1 = central_gradient(shape.f, x, H)
        g2 = central_gradient(shape.f, x, 2 * H)
        kink = np.max(np.abs(g1 - g2), axis=-1) > 1e-6
        dev = np.abs(np.linalg.norm(g1, axis=-1) - 1)[~kink]
        worst, frac = float(dev.max()), float(kink.mean())
        trials.append(Trial(shape.name, worst <= TOL and frac <= 0.01, {"max_dev": worst, "kink_fraction": frac}))
        key[f"{shape.name}: max ||∇φ|−1|"] = worst
        key[f"{shape.name}: kink fraction"] = frac
        hist.append((shape.name, dev))
    fig, (ax,) = figure(1, 1, 6.5, 4)
    for name, dev in hist:
        ax.hist(np.log10(np.maximum(dev, 1e-17)), bins=60, histtype="step", label=name)
    ax.set_xlabel("log10 ||∇φ| − 1| (dimensionless)")
    ax.set_ylabel("points")
    ax.legend(fontsize=7)
    return Evidence(trials, key, fig)
