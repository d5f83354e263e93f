"""Claim 7: implicit differentiation of the hit depth (eqs. 7–8) and the "forward trick" give the analytic
dt/dθ; how the error grows as ⟨∇φ, v⟩ → 0 (lecture, "Surface Rendering"; Niemeyer et al. CVPR 2020,
Yariv et al. NeurIPS 2020).

Scene: the reference unit sphere, θ = (c_x, c_y, c_z, r).  Rays along −z at impact parameter b from
the centre; exact derivative (from t = o_z − c_z − √(r² − b²)):

    dt/dθ = (−b/s, 0, −1, −r/s),   s = √((r − b)(r + b)) = r·|⟨n, v⟩|,

with r − b exact (Sterbenz) so the truth keeps full relative precision at grazing incidence.  The hit
x0 = o + t v comes from float64 bisection stopped at |φ| ≤ τ (τ = 0: the correctly rounded exact hit),
modelling a root finder of tolerance τ.  ∂σ/∂x0 and ∂σ/∂θ by torch autograd (float64) through the
reference scene's own array-API formula (``Field.value(x, xp, theta)``).
"""

from __future__ import annotations

import numpy as np

from reference import Sphere

from .figures import figure
from .ledger import LEDGER, Evidence, Trial
from .scenes import implicit_and_trick, sphere_dt_truth
from .stats import fit_power

RTOL = 1e-6
BANDS = ((0.1, 1.01, "|⟨n,v⟩| ≥ 0.1"), (1e-3, 0.1, "1e-3 ≤ |⟨n,v⟩| < 0.1"), (0.0, 1e-3, "|⟨n,v⟩| < 1e-3"))


def _rays(ks):
    b = np.concatenate([[0.0, 0.5], 1.0 - 10.0 ** -np.asarray(ks, float)])
    o = np.stack([b, np.zeros_like(b), np.full_like(b, 3.0)], -1)
    d = np.tile([0.0, 0.0, -1.0], (b.size, 1))
    return o, d, b


def hit_to_tolerance(f, o, d, lo, hi, tau):
    """Bisection on [lo, hi] (one sign change, φ(lo) > 0) until |φ| ≤ τ or the bracket is one ulp."""
    lo, hi = lo.copy(), hi.copy()
    t = 0.5 * (lo + hi)
    for _ in range(200):
        t = 0.5 * (lo + hi)
        v = f(o + t[:, None] * d)
        done = (np.abs(v) <= tau) | (t == lo) | (t == hi)
        if done.all():
            break
        lo = np.where(~done & (v > 0), t, lo)
        hi = np.where(~done & (v <= 0), t, hi)
    return t


@LEDGER.claim(
    "7",
    statement="implicit differentiation ∂t/∂θ = −(∂σ/∂θ)/⟨∂σ/∂x0, v⟩ (and the forward trick) gives the "
    "hit-depth derivative; behaviour as ⟨∇σ, v⟩ → 0",
    equation="eqs. (7)–(8) and the forward-trick formula, slide 'Surface Rendering'",
    how_checked="unit sphere, θ=(c,r), rays at impact 0, 0.5 and 1−10^-k (k=1..12); hit by bisection to "
    "|φ|≤τ (τ = exact, 1e-12, 1e-8); relative error ‖dt/dθ − exact‖/‖exact‖; a trial (method × τ × "
    f"band of |⟨n,v⟩|) holds if every ray in it has relative error ≤ {RTOL:g}; fitted slope of error vs |⟨n,v⟩|",
    scope="rays that hit transversally (⟨∇σ, v⟩ ≠ 0), at the exact hit or at a hit found to |φ| ≤ τ, as a "
    "root finder returns it; named class: well-conditioned rays, τ ≤ tolerance·|⟨n,v⟩|² (the error of eq. 8 "
    "at a τ-hit is about τ/|⟨n,v⟩|² relative), which includes every exact hit",
)
def check_implicit(ctx):
    ks = np.arange(1, 13) if ctx.quick else np.linspace(1, 13, 49)
    o, d, b = _rays(ks)
    scene = Sphere()
    truth, cos = sphere_dt_truth(b)
    t_exact = scene.first_hit(o, d)
    trials, key, curves = [], {}, []
    lo = np.zeros(b.size)
    hi = 3.0 - np.zeros(b.size)  # the chord midpoint (z = 0) is inside the sphere for every b < 1
    for tau_name, tau in (("exact hit", None), ("τ=1e-12", 1e-12), ("τ=1e-8", 1e-8)):
        t = t_exact if tau is None else hit_to_tolerance(scene.value, o, d, lo, hi, tau)
        imp, trick = implicit_and_trick(scene, o, d, t)
        for mname, g in (("implicit eq. 8", imp), ("forward trick", trick)):
            err = np.linalg.norm(g - truth, axis=-1) / np.linalg.norm(truth, axis=-1)
            for lo_c, hi_c, band in BANDS:
                m = (cos >= lo_c) & (cos < hi_c)
                if m.any():
                    worst = float(err[m].max())
                    conditioned = tau is None or tau <= RTOL * float(cos[m].min()) ** 2
                    trials.append(Trial(f"{mname}, {tau_name}, {band}", worst <= RTOL, {"max_rel_err": worst},
                                        classes=("well-conditioned: τ ≤ tol·|⟨n,v⟩|²",) if conditioned else ()))
            if mname.startswith("implicit"):
                curves.append((tau_name, err))
                sel = cos < 0.5
                try:
                    s, _ = fit_power(cos[sel], err[sel])
                except ValueError:
                    s = float("nan")
                key[f"{tau_name}: slope of log rel err vs log |⟨n,v⟩|"] = s
                key[f"{tau_name}: rel err at |⟨n,v⟩|={cos[-1]:.1e}"] = float(err[-1])
        key[f"{tau_name}: max |implicit − trick|"] = float(np.max(np.abs(imp - trick)))
    fig, (ax,) = figure(1, 1, 6.5, 4.5)
    for name, err in curves:
        ax.loglog(cos, np.maximum(err, 1e-17), "o-", ms=3, label=f"implicit, hit {name}")
    ax.axhline(RTOL, color="k", ls=":", label=f"criterion {RTOL:g}")
    ax.set_xlabel("|⟨n, v⟩| = cos(incidence) (dimensionless)")
    ax.set_ylabel("relative error of dt/dθ (dimensionless)")
    ax.invert_xaxis()
    ax.legend(fontsize=7)
    return Evidence(trials, key, fig)
