"""Claim 1: Boolean operations of implicit functions (lecture, "Properties - Boolean").

Two overlapping spheres A, B (exact SDFs φ1, φ2).  The exact SDF of each CSG result is known in
closed form: every boundary piece is a spherical cap of A or B bounded by the circle ∂A ∩ ∂B, and
the closest point of a cap (a geodesic disc) to x is the radial projection of x when that lies in
the cap, else the closest point of the rim circle.  So

    d(x, ∂R) = min over the caps of R's boundary of (| |x − c| − r |  or  dist(x, rim circle)),

signed by membership in R (membership is set logic on x ∈ A, x ∈ B).  This truth is independent
of the min/max formulas being checked.
"""

from __future__ import annotations

import numpy as np

from . import adapters
from .figures import figure
from .ledger import LEDGER, Evidence, Trial

CA, RA = np.array([-0.5, 0.0, 0.0]), 1.0
CB, RB = np.array([0.6, 0.1, 0.0]), 0.8


def _rim(x):
    """Distance from x to the circle ∂A ∩ ∂B."""
    u = CB - CA
    D = np.linalg.norm(u)
    u = u / D
    a = (D**2 + RA**2 - RB**2) / (2 * D)
    rc = np.sqrt(RA**2 - a**2)
    w = x - (CA + a * u)
    z = w @ u
    rho = np.linalg.norm(w - z[..., None] * u, axis=-1)
    return np.hypot(rho - rc, z)


def _cap_dist(x, c, r, other_c, other_r, keep_outside: bool):
    """Distance from x to the cap of sphere (c, r) lying outside (or inside) sphere (other_c, other_r)."""
    v = x - c
    n = np.linalg.norm(v, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):  # x at a centre: measure zero
        p = c + r * v / n[..., None]
    out = np.linalg.norm(p - other_c, axis=-1) >= other_r
    in_cap = out if keep_outside else ~out
    return np.where(in_cap, np.abs(n - r), _rim(x))


def exact_csg_sdf(x, op: str):
    inA = np.linalg.norm(x - CA, axis=-1) < RA
    inB = np.linalg.norm(x - CB, axis=-1) < RB
    capA_out = _cap_dist(x, CA, RA, CB, RB, True)
    capA_in = _cap_dist(x, CA, RA, CB, RB, False)
    capB_out = _cap_dist(x, CB, RB, CA, RA, True)
    capB_in = _cap_dist(x, CB, RB, CA, RA, False)
    if op.startswith("union"):
        inside, d = inA | inB, np.minimum(capA_out, capB_out)
    elif op.startswith("intersection"):
        inside, d = inA & inB, np.minimum(capA_in, capB_in)
    elif op.startswith("complement"):
        inside, d = ~inA, np.abs(np.linalg.norm(x - CA, axis=-1) - RA)
    elif op.startswith("difference"):
        inside, d = inA & ~inB, np.minimum(capA_out, capB_in)
    else:  # pragma: no cover
        raise ValueError(op)
    return np.where(inside, -d, d), inside


def _samples(ctx):
    rng = np.random.default_rng(ctx.seed)
    n = 20_000 if ctx.quick else 400_000
    return rng.uniform(-2.2, 2.2, (n, 3))


def _fields(x):
    fA = adapters.sphere_shape(RA, CA).f(x)
    fB = adapters.sphere_shape(RB, CB).f(x)
    return {op: fn(fA, fB) for op, fn in adapters.CSG_OPS.items()}


@LEDGER.claim(
    "1a",
    statement="min(φ1,φ2) is the union, max(φ1,φ2) the intersection, −φ1 the complement and max(φ1,−φ2) "
    "the subtraction of the interior regions",
    equation="slide 'Properties - Boolean'",
    how_checked="two overlapping sphere SDFs; at random points in [−2.2,2.2]³ the sign of each formula is "
    "compared with set membership (x∈A, x∈B by |x−c|<r); a trial (one operation) holds if every point "
    "farther than 1e-12 from the boundary has the right sign",
)
def check_regions(ctx):
    x = _samples(ctx)
    trials, key = [], {}
    for op, phi in _fields(x).items():
        sdf, inside = exact_csg_sdf(x, op)
        ok = np.abs(sdf) > 1e-12
        wrong = int(np.sum(((phi < 0) != inside) & ok))
        trials.append(Trial(op, wrong == 0, {"wrong_sign_points": wrong, "points": int(ok.sum())}))
        key[f"{op.split()[0]}_wrong"] = wrong
    fig = _slice_figure()
    return Evidence(trials, key, fig)


@LEDGER.claim(
    "1b",
    statement="the Boolean results are again signed distance functions (how far from exact, inside and "
    "outside)",
    equation="slide 'Properties - Boolean' (implicit when CSG results are sphere-traced)",
    how_checked="same points; exact SDF of each CSG region in closed form (caps + rim circle); a trial "
    "(operation × side) holds if max|φ_op − SDF| ≤ 1e-12 on that side; also reports whether |φ_op| ≤ |SDF| "
    "(a distance bound, safe for sphere tracing)",
)
def check_sdf(ctx):
    x = _samples(ctx)
    trials, key = [], {}
    for op, phi in _fields(x).items():
        sdf, inside = exact_csg_sdf(x, op)
        for side, m in (("outside", ~inside), ("inside", inside)):
            err = float(np.max(np.abs(phi[m] - sdf[m]))) if m.any() else 0.0
            bound = bool(np.all(np.abs(phi[m]) <= np.abs(sdf[m]) + 1e-12))
            short = op.split()[0]
            trials.append(Trial(f"{op} {side}", err <= 1e-12, {"max_abs_err": err, "is_distance_bound": bound}))
            key[f"{short}_{side}_max_err"] = err
            key[f"{short}_{side}_bound"] = bound
    return Evidence(trials, key, _slice_figure())


def _slice_figure():
    g = np.linspace(-2.0, 2.0, 241)
    X, Y = np.meshgrid(g, g)
    P = np.stack([X, Y, np.zeros_like(X)], -1)
    fig, axes = figure(4, 1, 3.4, 3.2)
    for ax, (op, phi) in zip(axes, _fields(P).items()):
        sdf, _ = exact_csg_sdf(P, op)
        im = ax.imshow(phi - sdf, extent=(-2, 2, -2, 2), origin="lower", cmap="RdBu_r", vmin=-0.6, vmax=0.6)
        ax.contour(X, Y, sdf, levels=[0], colors="k", linewidths=1)
        ax.set_title(f"{op}\nφ_op − exact SDF (z=0)", fontsize=8)
        ax.set_xlabel("x (length units)")
        ax.set_ylabel("y (length units)")
    fig.colorbar(im, ax=axes, shrink=0.8, label="φ_op − SDF (length units)")
    return fig
