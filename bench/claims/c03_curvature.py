"""Claim 3: "the mean curvature of the interface is Δφ = φxx + φyy + φzz" (lecture, "Properties -
Mean Curvature").

Convention (isobench, ``reference.curvature``; truth from the reference scenes' ``curvatures_exact``): principal curvatures κ1, κ2 with
the outward normal, a sphere of radius r has κ = +1/r.  Mean curvature H = (κ1 + κ2)/2; the level-set
literature (Osher & Fedkiw, *Level Set Methods*, §1.4) calls κ = ∇·(∇φ/|∇φ|) = κ1 + κ2 "the
curvature".  For an exact SDF (|∇φ| = 1) ∇·(∇φ/|∇φ|) = Δφ, so on its zero set Δφ = κ1 + κ2 = 2H; for
other φ the two differ.  Each (shape, convention) pair is one trial.

Δφ by the 7-point stencil with h = 1e-3: truncation h²/12·|∂⁴φ| ≲ 1e-6 on these shapes, rounding
≈ 6ε|φ|/h² ≈ 1e-9, so the 1e-4 relative tolerance is two orders above the measurement error.
"""

from __future__ import annotations

import numpy as np

from reference import AlgebraicSphere, Scaled, Sphere

from .adapters import curvature_sum, label
from .scenes import surface_points, torus
from .figures import figure
from .ledger import LEDGER, Evidence, Trial
from .stats import central_gradient, central_laplacian

H_LAP = 1e-3
RTOL = 1e-4


def _div_normal(f, x, h=1e-4):
    """∇·(∇φ/|∇φ|) by central differences of the normalised gradient (inner h = 1e-6)."""

    def ncomp(k):
        def g(y):
            gr = central_gradient(f, y, 1e-6)
            return gr[..., k] / np.linalg.norm(gr, axis=-1)

        return g

    out = 0.0
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        out = out + (ncomp(k)(x + e) - ncomp(k)(x - e)) / (2 * h)
    return out


@LEDGER.claim(
    "3",
    statement="the mean curvature of the interface is the Laplacian Δφ = φxx + φyy + φzz",
    equation="slide 'Properties - Mean Curvature'",
    how_checked="surface points of sphere SDFs (r = 1, 0.5), a torus SDF, the lecture's x²+y²+z²−1 and 2·SDF; "
    "Δφ by the 7-point stencil (h=1e-3) against the exact κ1+κ2 (sum convention) and against "
    "H = (κ1+κ2)/2 (mean convention); a trial (shape × convention) holds if max |Δφ − truth| ≤ 1e-4·max(1,|truth|)",
    scope="any implicit φ (the slide speaks of 'the implicit function'), at surface points; named class: exact "
    "SDFs with the curvature read as the sum κ1+κ2 (Osher & Fedkiw's convention, κ = ∇·(∇φ/|∇φ|))",
)
def check_laplacian(ctx):
    rng = np.random.default_rng(ctx.seed + 3)
    n = 500 if ctx.quick else 20_000
    sph = Sphere()
    cases = [
        ("sphere", sph, 1.0),
        ("sphere", Sphere(radius=0.5), 0.5),
        ("torus", torus(), 1.0),
        ("sphere", AlgebraicSphere(), 1.0),
        ("sphere", Scaled(sph, 2.0), 1.0),
    ]
    trials, key, pts = [], {}, []
    for fam, shape, scale in cases:
        x = scale * surface_points(fam, n, rng)
        lap = central_laplacian(shape.value, x, H_LAP)
        ksum = curvature_sum(shape, x)
        name = label(shape)
        for conv, truth in (("sum κ1+κ2", ksum), ("mean (κ1+κ2)/2", ksum / 2)):
            err = float(np.max(np.abs(lap - truth) / np.maximum(1.0, np.abs(truth))))
            sdf_sum = shape.info.exact_sdf and conv.startswith("sum")
            trials.append(Trial(f"{name}, curvature read as {conv}", err <= RTOL,
                                {"max_rel_err": err, "lap_median": float(np.median(lap)),
                                 "truth_median": float(np.median(truth))},
                                classes=("exact SDFs, curvature read as κ1+κ2",) if sdf_sum else ()))
        key[f"{name}: median Δφ"] = float(np.median(lap))
        key[f"{name}: median κ1+κ2"] = float(np.median(ksum))
        pts.append((name, ksum, lap))
    # the formula that does hold for any φ with ∇φ ≠ 0: κ1 + κ2 = ∇·(∇φ/|∇φ|)
    alg = AlgebraicSphere()
    x = surface_points("sphere", 50, rng)
    key["x²+y²+z²−1: max |∇·(∇φ/|∇φ|) − (κ1+κ2)|"] = float(
        np.max(np.abs(_div_normal(alg.value, x) - curvature_sum(alg, x))))
    key["convention"] = "κ>0 for a sphere with outward normal; H=(κ1+κ2)/2"

    fig, (ax,) = figure(1, 1, 6.5, 4.5)
    for name, k, lap in pts:
        ax.plot(k, lap, ".", ms=3, label=name)
    lim = np.array([min(p[1].min() for p in pts) - 0.5, max(p[1].max() for p in pts) + 0.5])
    ax.plot(lim, lim, "k-", lw=0.8, label="Δφ = κ1+κ2")
    ax.plot(lim, lim / 2, "k:", lw=0.8, label="Δφ = H = (κ1+κ2)/2")
    ax.set_xlabel("exact κ1 + κ2 (1/length)")
    ax.set_ylabel("Δφ at surface points (1/length; ×k for k·φ)")
    ax.legend(fontsize=7)
    return Evidence(trials, key, fig)
