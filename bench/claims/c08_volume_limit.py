"""Claim 8: "when sampling densely around the surface, volume rendering → surface rendering":
lim_{Δ→0, N→∞} ‖C(r) − ρ(x_s)‖ = 0 (lecture eqs. 13/15), for each density model.

Scene: the reference unit sphere SDF; rays along −z at impact parameters 0…0.9 (no grazing); colour
ρ(x) with Lipschitz constant γ = 1 (``adapters.colour_field``); exact surface point x_s from the
reference first hit.  N samples at the midpoints of [t_s − Δ, t_s + Δ] (every sample within Δ of x_s,
the lecture's Δ); opacities from each density model with sharpness s (``adapters.density_alphas``);
compositing by eqs. 9–10 (``rendering.composite``, no background).  Error = max over rays of
|C − ρ(x_s)|.
"""

from __future__ import annotations

import numpy as np

from reference import Sphere

from . import adapters
from .figures import figure
from .ledger import LEDGER, Evidence, Trial
from .rendering import composite, window_samples
from .stats import fit_power

GAMMA = 1.0


def setup(n_rays=12):
    b = np.linspace(0.0, 0.9, n_rays)
    o = np.stack([b, 0.3 * b, np.full_like(b, 3.0)], -1)
    d = np.tile([0.0, 0.0, -1.0], (b.size, 1))
    scene = Sphere()
    t_s = scene.first_hit(o, d)
    rho = adapters.colour_field(GAMMA)
    return scene, o, d, t_s, rho


def render_error(model, s, delta, n, scene, o, d, t_s, rho):
    mids, lo, hi, dl = window_samples(t_s, delta, n)
    pts = o[:, None, :] + mids[..., None] * d[:, None, :]
    phi = scene.value(pts)
    phi_lo = scene.value(o[:, None, :] + lo[..., None] * d[:, None, :])
    phi_hi = scene.value(o[:, None, :] + hi[..., None] * d[:, None, :])
    alpha = adapters.density_alphas(model, phi, phi_lo, phi_hi, dl, s)
    c, _ = composite(alpha, rho(pts))
    xs = o + t_s[:, None] * d
    return float(np.max(np.abs(c - rho(xs))))


def _path(quick):
    j = np.arange(7 if quick else 11)
    return 10.0 ** (-j / 2), 4 * 2**j  # Δ: 1 → 1e-3 (1e-5), N: 4 → 256 (4096)


def path_trial(errs):
    """'Tends to 0' along the path, operationally: the error at the path's end is ≤ 1e-2 (1% of the colour
    range; the stated tolerance of the check)."""
    return bool(np.asarray(errs)[-1] <= 1e-2)


@LEDGER.claim(
    "8",
    statement="volume rendering tends to surface rendering: lim_{Δ→0, N→∞} ‖C(r) − ρ(x_s)‖ = 0",
    equation="eqs. (13) and (15)",
    how_checked="unit-sphere SDF, 12 rays, colour with γ=1; N samples in [t_s−Δ, t_s+Δ], eqs. 9–10 with "
    "opacities from each density model (UNISURF occupancy, NeRF-style logistic density, VolSDF Laplace, NeuS) "
    "of sharpness s; along the path Δ = 10^(−j/2), N = 4·2^j (j=0..6; full: 0..10) at fixed s ∈ {10, 1000} and "
    "at s = 100/Δ; a trial (model × s) holds if the final error max_rays |C − ρ(x_s)| ≤ 1e-2; fitted rates "
    "over Δ, N and 1/s in the key numbers",
)
def check_limit(ctx):
    scene, o, d, t_s, rho = setup()
    deltas, ns = _path(ctx.quick)
    trials, key, paths = [], {}, {}
    for model in adapters.DENSITY_MODELS:
        for s_label, s_of in (("s=10", lambda dl: 10.0), ("s=1000", lambda dl: 1000.0), ("s=100/Δ", lambda dl: 100 / dl)):
            errs = [render_error(model, s_of(dl), dl, n, scene, o, d, t_s, rho) for dl, n in zip(deltas, ns)]
            trials.append(Trial(f"{model}, {s_label}", path_trial(errs), {"final_err": errs[-1], "first_err": errs[0]}))
            paths[(model, s_label)] = errs
        # rates: one knob varied, the others at their most accurate grid value
        grid_d = np.logspace(0, -3, 7)
        grid_n = np.array([4, 16, 64, 256, 1024] + ([] if ctx.quick else [4096]))
        grid_s = np.logspace(1, 4, 7)
        e_d = [render_error(model, 1e4, dl, int(grid_n[-1]), scene, o, d, t_s, rho) for dl in grid_d]
        e_n = [render_error(model, 1e4, 0.1, int(n), scene, o, d, t_s, rho) for n in grid_n]
        e_s = [render_error(model, s, 1.0, int(grid_n[-1]), scene, o, d, t_s, rho) for s in grid_s]
        for nm, x, e in (("Δ", grid_d, e_d), ("N", grid_n, e_n), ("1/s", 1 / grid_s, e_s)):
            try:
                key[f"{model}: error ∝ {nm}^rate, rate"] = fit_power(x, e)[0]
            except ValueError:
                key[f"{model}: error ∝ {nm}^rate, rate"] = float("nan")
            key[f"{model}: error range over {nm}"] = [float(min(e)), float(max(e))]
        key[f"{model}: final error along path (s=10, s=1000, s=100/Δ)"] = [
            paths[(model, lab)][-1] for lab in ("s=10", "s=1000", "s=100/Δ")]

    # the error surface over (Δ, N) at one sharpness, per model (second row of the figure)
    hm_d = np.logspace(0, -3, 7)
    hm_n = np.array([4, 16, 64, 256, 1024])
    surfaces = {m: np.array([[render_error(m, 1000.0, dl, int(n), scene, o, d, t_s, rho) for n in hm_n] for dl in hm_d])
                for m in adapters.DENSITY_MODELS}

    fig, axes = figure(4, 2, 3.6, 3.4)
    for ax, model in zip(axes[4:], adapters.DENSITY_MODELS):
        im = ax.imshow(np.log10(np.maximum(surfaces[model], 1e-17)), origin="lower", aspect="auto", cmap="viridis",
                       vmin=-8, vmax=0)
        ax.set_xticks(range(hm_n.size), [str(n) for n in hm_n])
        ax.set_yticks(range(hm_d.size), [f"{x:.0e}" for x in hm_d])
        ax.set_xlabel("N (samples)")
        ax.set_ylabel("Δ (length units)")
        ax.set_title(f"{model}, s=1000: log10 max |C − ρ(x_s)|", fontsize=8)
    fig.colorbar(im, ax=axes[4:], shrink=0.8, label="log10 error (colour units)")
    for ax, model in zip(axes[:4], adapters.DENSITY_MODELS):
        for lab in ("s=10", "s=1000", "s=100/Δ"):
            ax.loglog(deltas, np.maximum(paths[(model, lab)], 1e-17), "o-", ms=3, label=lab)
        ax.axhline(1e-2, color="k", ls=":", lw=0.8)
        ax.invert_xaxis()
        ax.set_title(f"{model}: path Δ→0, N=4·2^j", fontsize=8)
        ax.set_xlabel("Δ (length units; N grows ×2 per ×√10 in Δ)")
        ax.set_ylabel("max |C − ρ(x_s)| (colour units)")
        ax.legend(fontsize=7)
    return Evidence(trials, key, fig)
