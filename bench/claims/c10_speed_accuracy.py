"""Claim 10: "volume rendering is quick but not accurate (NeRF), while surface rendering is accurate but
slow/complicated" — put numbers on it with time-versus-error curves (lecture, "Take-Home Message" and
"Surface Rendering: Cons/Pros").

Same image, same colour field, same truth: the reference unit sphere seen by a pinhole camera, the
reference RGB colour field (``SineColor``, Lipschitz constant 1) at the exact first hit (background 0
for misses).
* Surface rendering: the numpy backend's ``sphere_trace`` (``adapters.prepare_trace``) swept over its
  tolerance, then ρ at the found hit.
* Volume rendering: N uniform samples on [0, 6] (the camera is at distance 3), opacities from a density
  model of fixed sharpness s = 200, eqs. 9–10; swept over N.
Time: median of repeated wall-clock runs of the rendering alone (numpy, one process; on a shared
machine the times are noisy: compare shapes of curves, not digits).  Error: the median over pixels of |C − C_exact|
(the max is dominated by silhouette pixels, where any volume model blends; it is reported too), pixel
error = ‖C − C_exact‖₂ over RGB.
"""

from __future__ import annotations


import os
import time

import numpy as np

from reference import Sphere

from . import adapters
from .figures import figure
from .ledger import LEDGER, Trial
from .rendering import composite
from .tracing import camera_rays

S_SHARP = 200.0
T_FAR = 6.0
W_EXACT = 0.5  # half-width of the window around the hit for the continuous integral
COS_MIN = 0.3  # pixels with |⟨n, d⟩| ≥ 0.3: outside the window NeuS's σ and T are ≤ e^{−s·W·0.3} = e^{−30}


def continuous_floor(scene, rho, o, d, t_exact, c_exact, pick, disk=None):
    """‖C_exact − C_surface‖ per picked pixel, C_exact the continuous NeuS integral (``render_exact``) on
    [t_s − W, t_s + W]: the error volume rendering at s = S_SHARP keeps for every N (its N → ∞ limit);
    each integral kept in ``disk`` between runs (:func:`bench.run.references.render_exact_kept`)."""
    from ..run.references import render_exact_kept

    out, bounds = [], []
    for i in pick:
        c, qb = render_exact_kept(disk, scene, rho, "neus", S_SHARP, o[[i]], d[[i]], t_exact[i] - W_EXACT,
                                  t_exact[i] + W_EXACT)
        out.append(float(np.linalg.norm(c[0] - c_exact[i])))
        bounds.append(float(qb[0]))
    return np.array(out), max(bounds)


def _median_time(fn, repeats):
    fn()  # warm-up (not timed)
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts)), out


def volume_render(scene, o, d, rho, n, model, s=S_SHARP, t_far=T_FAR):
    edges = np.linspace(0.0, t_far, n + 1)
    mids = 0.5 * (edges[:-1] + edges[1:])
    pts = o[:, None, :] + mids[None, :, None] * d[:, None, :]
    phi = scene.value(pts)
    lo = scene.value(o[:, None, :] + edges[None, :-1, None] * d[:, None, :]) if model == "neus" else phi
    hi = scene.value(o[:, None, :] + edges[None, 1:, None] * d[:, None, :]) if model == "neus" else phi
    alpha = adapters.density_alphas(model, phi, lo, hi, np.full(phi.shape, t_far / n), s)
    c, _ = composite(alpha, rho(pts))
    return c


_HOW = ("pinhole image of the unit sphere, colour γ=1; surface: backend sphere tracing swept over tol "
        "1e-1…1e-12; volume: N=8…1024 uniform samples, reference density models (UNISURF occupancy, NeuS) at s=200; error = median "
        "pixel error; trials per model: 'volume not accurate' holds if its best error exceeds surface rendering's best; 'surface slow' "
        "holds if reaching the volume's best error takes surface rendering longer than volume rendering; "
        "NeuS's N→∞ limit (reference render_exact on [t_s−0.5, t_s+0.5], 2 front-facing pixels, full: 8): 'not "
        "accurate for any N' holds if its smallest error exceeds surface rendering's best median error",)


def _speed(ctx):
    """Trials of claims 10a (accuracy) and 10b (speed), measured once: (part → trials, key, figure)."""
    n_side = 24 if ctx.quick else 64
    repeats = 3 if ctx.quick else 5
    scene = Sphere()
    o, d = camera_rays(n_side, eye=(0.0, 0.0, 3.0), fov_deg=45.0)
    rho = adapters.colour_field(1.0)
    t_exact = scene.first_hit(o, d)
    hit = np.isfinite(t_exact)
    c_exact = np.where(hit[:, None], rho(o + np.where(hit, t_exact, 0)[:, None] * d), 0.0)

    surf = []
    for tol in 10.0 ** -np.arange(1, 13):
        run, to_np = adapters.prepare_trace(scene, o, d, tol=float(tol), max_steps=10_000, t_max=T_FAR)
        tm, out = _median_time(run, repeats)
        t, status, _ = to_np(out)
        found = np.isfinite(t) & (status == 0)
        c = np.where(found[:, None], rho(o + np.where(found, t, 0)[:, None] * d), 0.0)
        e = np.linalg.norm(c - c_exact, axis=-1)
        surf.append((float(tol), tm, float(np.median(e)), float(np.max(e))))
    vol = {}
    for model in ("unisurf", "neus"):
        rows = []
        for n in (8, 16, 32, 64, 128, 256, 512, 1024):
            tm, c = _median_time(lambda: volume_render(scene, o, d, rho, n, model), repeats)
            e = np.linalg.norm(c - c_exact, axis=-1)
            rows.append((n, tm, float(np.median(e)), float(np.max(e))))
        vol[model] = rows

    # the exact N → ∞ limit of the NeuS volume renderer on a few front-facing pixels
    cos_nd = np.abs(np.einsum("ij,ij->i", scene.normal_exact(o + np.where(hit, t_exact, 0)[:, None] * d), d))
    eligible = np.flatnonzero(hit & (cos_nd >= COS_MIN))
    pick = np.sort(np.random.default_rng(ctx.seed + 10).choice(eligible, 2 if ctx.quick else 8, replace=False))
    floors, floor_bound = continuous_floor(scene, rho, o, d, t_exact, c_exact, pick, ctx.reference_dir)

    trials, key = [], {}
    s_err = np.array([r[2] for r in surf])
    s_time = np.array([r[1] for r in surf])
    best_surface = float(s_err.min())
    key["surface: best median error"] = best_surface
    key["surface: (tol, time s, median error, max error)"] = [[r[0], round(r[1], 6), r[2], r[3]] for r in surf]
    for model, rows in vol.items():
        v_err = np.array([r[2] for r in rows])
        v_time = np.array([r[1] for r in rows])
        best_v = float(v_err.min())
        t_v = float(v_time[np.argmin(v_err)])
        reach = s_err <= best_v
        t_s = float(s_time[reach].min()) if reach.any() else float("inf")
        trials.append(("10a", Trial(f"{model} (s={S_SHARP:g}): volume not accurate", best_v > best_surface,
                                    {"volume_best_err": best_v, "surface_best_err": best_surface})))
        trials.append(("10b", Trial(f"{model} (s={S_SHARP:g}): surface slower at the volume's best error", t_s > t_v,
                                    {"surface_time_s": t_s, "volume_time_s": t_v, "error_level": best_v})))
        key[f"{model}: best median error"] = best_v
        key[f"{model}: (N, time s, median error, max error)"] = [[r[0], round(r[1], 6), r[2], r[3]] for r in rows]
    trials.append(("10a", Trial(f"neus (s={S_SHARP:g}): volume not accurate for any N (continuous-integral limit "
                                f"on {pick.size} front-facing pixels, smallest)", float(floors.min()) > best_surface,
                                {"limit_err_min": float(floors.min()), "surface_best_err": best_surface})))
    key["neus: N→∞ limit error ‖C_exact − C_surface‖ on picked pixels"] = floors.tolist()
    key["neus: render_exact error bound"] = floor_bound
    key["rays"] = int(o.shape[0])
    key["timing note"] = "median of %d runs, numpy, %d logical CPUs (a shared machine is noisy)" % (repeats, os.cpu_count() or 0)

    fig, (ax,) = figure(1, 1, 6.5, 4.5)
    ax.loglog([r[2] for r in surf], [r[1] for r in surf], "o-", label="surface: sphere tracing, tol sweep")
    for model, rows in vol.items():
        ax.loglog([r[2] for r in rows], [r[1] for r in rows], "s--", label=f"volume: {model}, N sweep")
    for f in floors:
        ax.axvline(f, color="grey", ls=":", lw=0.8)
    ax.axvline(floors.min(), color="grey", ls=":", lw=0.8, label="neus N→∞ limit error (render_exact), picked pixels")
    ax.set_xlabel("median pixel error ‖C − C_exact‖ (colour units)")
    ax.set_ylabel("median render time (s)")
    ax.legend(fontsize=7)
    return {p: [t for q, t in trials if q == p] for p in ("10a", "10b")}, key, fig


LEDGER.parts(_speed, [
    dict(id="10a",
         statement="volume rendering is not accurate, surface rendering is accurate",
         equation="slides 'Surface Rendering (Cons/Pros)' and 'Take-Home Message'",
         how_checked=_HOW,
         scope="rendering a surface (the sphere) at the accuracy each renderer can reach: any N for volume rendering "
         "(including the continuous limit N → ∞) against surface rendering's best tolerance"),
    dict(id="10b",
         statement="volume rendering is quick, surface rendering is slow",
         equation="slides 'Surface Rendering (Cons/Pros)' and 'Take-Home Message'",
         how_checked=_HOW,
         scope="the same image rendered to the same error: time of surface rendering to reach the volume renderer's "
         "best error against the volume renderer's time there (numpy, one machine)"),
])
