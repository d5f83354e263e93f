"""Surface extraction as a method family: implicit φ → triangle mesh by marching cubes, scored
against the exact surface, swept over the grid resolution (a time-versus-error curve).

The method (:func:`extract`): sample φ with numpy on a regular grid of N³ points over a box
containing the surface (the scene's bounding cube padded by one cell: spacing h = 2r/(N − 3)
for a bounding ball of radius r, so that the zero set lies at least one cell inside the box
and the mesh is closed), then ``skimage.measure.marching_cubes(φ, level=0, spacing=(h, h, h))``
(Lewiner et al., "Efficient implementation of marching cubes' cases with topological
guarantees", JGT 2003; the vertices are linear interpolations of φ along cell edges).  For a
smooth surface the vertices are O(h²) from it (linear interpolation of a C² function) and the
faces' chords add O(h² κ), so the Hausdorff distance falls like h²; features thinner than h are
lost (the mesh misses them and the surface → mesh side of the distance sees it).

The score (:func:`reference.surface_distance.mesh_to_surface_errors`, float64): Hausdorff
H = max of the two directed maxima, Chamfer C = mean of the two directed means (unsquared,
area-weighted on the mesh).  Sampling density: every face of the mesh carries a barycentric
grid of level 3 (covering radius ρ_M ≤ longest edge / 3 ≤ 0.58 h), and the exact surface is
sampled with covering radius ρ_S ≤ h/2 (certified for exact SDFs and meshes).  The sampled H is
a lower bound of the true one, by at most max(ρ_M, ρ_S) (the distances are 1-Lipschitz; on
smooth parts the gap is O(ρ² κ)); both ρ are in every row (``covering_mesh``,
``covering_surface``).

Rows (:func:`run_extraction`): family ``extract``, method ``marching_cubes``, backend
``numpy``, dtype ``float64``, knob ``resolution=N``; two rows per (case, N) with the same
timing, quantity ``hausdorff`` (``error_max`` = H) and quantity ``chamfer`` (``error_max`` =
C); on both ``error_median`` / ``error_p99`` are the median / 99th percentile of all pointwise
distances (both directions), unit ``length``.  ``time_*`` is sampling plus extraction per
repeat (``time_sample_s``, ``time_extract_s``: their medians).  ``reference_error_bound`` is
the bound on the distances themselves (rounding for exact SDFs and meshes; the Lipschitz
bracket's width for the fallback), not the sampling gap.
"""

from __future__ import annotations

import json
import math
import time
import traceback
from pathlib import Path
from typing import Iterable

import numpy as np
import pandas as pd

FAMILY = "extract"
METHOD = "marching_cubes"
QUANTITIES = ("hausdorff", "chamfer")
#: barycentric grid level on the extracted mesh's faces
FACE_LEVEL = 3
#: surface samples' covering radius, in grid spacings
SURFACE_SPACING = 0.5


def grid_box(scene, resolution: int, bounds=None) -> tuple[np.ndarray, np.ndarray]:
    """``(lo (3,), spacing (3,))`` of the N³ grid: from ``bounds = (lo, hi)`` as given, else the
    scene's bounding cube [c − r − h, c + r + h] with h = 2r/(N − 3) (padded by one cell)."""
    if not isinstance(resolution, (int, np.integer)) or resolution < 4:
        raise ValueError(f"resolution must be an integer ≥ 4 (grid points per axis), got {resolution!r}")
    n = int(resolution)
    if bounds is not None:
        lo, hi = (np.asarray(b, np.float64).reshape(3) for b in bounds)
        if not np.all(np.isfinite(lo) & np.isfinite(hi) & (hi > lo)):
            raise ValueError(f"bounds must be (lo, hi) with finite lo < hi per axis, got {bounds!r}")
        return lo, (hi - lo) / (n - 1)
    ball = scene.bounding_sphere()
    if ball is None:
        raise ValueError(f"{type(scene).__name__} has no bounding sphere (scene.bounding_sphere() is None): "
                         "pass bounds=(lo, hi), a box containing the surface")
    c, r = np.asarray(ball[0], np.float64), float(ball[1])
    h = 2 * r / (n - 3)
    return c - r - h, np.full(3, h)


def extract(scene, resolution: int, bounds=None) -> dict:
    """Marching cubes of φ = 0 on an N³ grid (module docstring).  Returns ``vertices`` (n, 3)
    float64 world coordinates, ``faces`` (m, 3) int64, ``spacing`` (3,), ``lo`` (3,),
    ``time_sample_s`` (building the grid and evaluating φ with numpy) and ``time_extract_s``
    (``marching_cubes``).  A grid on which φ does not change sign gives an empty mesh (no
    surface found); a non-finite φ raises ValueError."""
    from skimage.measure import marching_cubes

    lo, h = grid_box(scene, resolution, bounds)
    n = int(resolution)
    t0 = time.perf_counter()
    axes = [lo[k] + h[k] * np.arange(n) for k in range(3)]
    x = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    phi = np.asarray(scene.value(x, np), np.float64)
    t1 = time.perf_counter()
    if not np.all(np.isfinite(phi)):
        raise ValueError(f"φ of {type(scene).__name__} is not finite at {int(np.sum(~np.isfinite(phi)))} grid points")
    if not (phi.min() < 0 < phi.max()):
        t2 = time.perf_counter()
        verts, faces = np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    else:
        verts, faces, _, _ = marching_cubes(phi, level=0.0, spacing=tuple(float(s) for s in h),
                                            allow_degenerate=False)
        t2 = time.perf_counter()
        verts = np.asarray(verts, np.float64) + lo
        faces = np.asarray(faces, np.int64)
    return {"vertices": verts, "faces": faces, "spacing": h, "lo": lo,
            "time_sample_s": t1 - t0, "time_extract_s": t2 - t1}


def applies(scene) -> str | None:
    """None if :func:`run_extraction` can score ``scene``, else the reason it cannot."""
    from reference.surface_distance import distance_method

    if scene.bounding_sphere() is None:
        return "no bounding sphere (scene.bounding_sphere() is None): no box to grid"
    if distance_method(scene) is None:
        return "no exact distance to the surface: not an exact SDF and no Lipschitz bound to certify one"
    return None


def default_cases() -> list:
    """One case per distinct scene of the catalog and the mesh cases (the first id in sorted
    order represents its scene): extraction depends on the scene only, not on the rays."""
    from reference.cases import catalog

    cases = list(catalog())
    try:
        from reference.mesh_cases import mesh_cases

        cases += [c for c in mesh_cases() if ".camera." in c.id]
    except ImportError:  # pragma: no cover - branch without meshes
        pass
    seen, out = set(), []
    for c in cases:
        h = c.scene.content_hash()
        if h not in seen:
            seen.add(h)
            out.append(c)
    return out


def _base(case, n: int | None, run_id: str) -> dict:
    from ..run.results import SCHEMA_VERSION

    return {"schema_version": SCHEMA_VERSION, "run_id": run_id, "case_id": case.id,
            "case_version": getattr(case, "version", ""), "backend": "numpy", "device": "cpu", "dtype": "float64",
            "method": METHOD, "family": FAMILY, "knob": f"resolution={n}" if n is not None else "",
            "knobs_json": json.dumps({"resolution": n}) if n is not None else "{}", "unit": "length"}


def _iqr(a) -> float:
    q1, q3 = np.percentile(a, [25, 75])
    return float(q3 - q1)


def run_extraction(cases: Iterable | None = None, resolutions=(16, 32, 64, 128), repeats: int = 3, *,
                   run_id: str = "", progress=None, stage=None) -> list[dict]:
    """Marching cubes at each resolution on each case's scene, scored and timed: a list of
    result rows (:mod:`bench.run.results` schema; module docstring for the columns).

    ``cases``: :class:`reference.cases.Case` objects (default :func:`default_cases`).  A case
    whose scene does not apply (:func:`applies`) gives one row per quantity with outcome
    ``skipped`` and the reason; a case that raises gives outcome ``failed`` rows with the
    traceback, for that resolution, and the others go on.  ``repeats`` ≥ 1 timed extractions per
    resolution (the error is measured once, on the first: the mesh is deterministic).
    ``progress``: called with a one-line string per configuration, when it is done; ``stage``
    (default ``progress``): with one as it starts (a :meth:`bench.run.heartbeat.Heartbeat.stage`
    keeps saying it while a slow one runs)."""
    stage = stage or progress
    if not isinstance(repeats, (int, np.integer)) or repeats < 1:
        raise ValueError(f"repeats must be an integer ≥ 1, got {repeats!r}")
    res = [int(r) for r in resolutions]
    for r in res:
        grid_box(None, r, bounds=((0, 0, 0), (1, 1, 1)))  # validates resolution values early
    from reference.surface_distance import mesh_to_surface_errors, surface_samples

    rows: list[dict] = []
    for case in (default_cases() if cases is None else cases):
        try:
            reason = applies(case.scene)
        except Exception as exc:  # a broken scene fails its own rows, not the run
            reason, tb = None, traceback.format_exc()
            for q in QUANTITIES:
                rows.append({**_base(case, None, run_id), "quantity": q, "outcome": "failed",
                             "reason": f"{type(exc).__name__}: {exc}", "traceback": tb})
            continue
        if reason is not None:
            for q in QUANTITIES:
                rows.append({**_base(case, None, run_id), "quantity": q, "outcome": "skipped", "reason": reason})
            if progress:
                progress(f"extract {case.id}: skipped ({reason})")
            continue
        for n in res:
            base = _base(case, n, run_id)
            if stage:
                stage(f"extract {case.id} N={n}: φ on {n}³ points and marching cubes ×{repeats}, then the distances "
                      "to the exact surface")
            try:
                runs = [extract(case.scene, n) for _ in range(repeats)]
                first = runs[0]
                h = float(np.max(first["spacing"]))
                t_ref = time.perf_counter()
                surf = surface_samples(case.scene, SURFACE_SPACING * h)
                m = mesh_to_surface_errors(case.scene, first["vertices"], first["faces"], SURFACE_SPACING * h,
                                           level=FACE_LEVEL, surface=surf)
                t_ref = time.perf_counter() - t_ref
            except Exception as exc:
                tb = traceback.format_exc()
                for q in QUANTITIES:
                    rows.append({**base, "quantity": q, "outcome": "failed",
                                 "reason": f"{type(exc).__name__}: {str(exc)[:300]}", "traceback": tb})
                if progress:
                    progress(f"extract {case.id} N={n}: failed ({type(exc).__name__})")
                continue
            common = _scored_row(base, runs, m, h, t_ref, n)
            for q in QUANTITIES:
                rows.append({**common, "quantity": q, "error_max": m[q]})
            if progress:
                progress(f"extract {case.id} N={n}: H {m['hausdorff']:.3g}, C {m['chamfer']:.3g}, "
                         f"{common['time_median_s']:.3g} s")
    return rows


def _scored_row(base: dict, runs: list[dict], m: dict, h: float, t_ref: float, n: int) -> dict:
    """The columns of one resolution's ok rows: the extractions' times ``runs``, the mesh's
    distances to the exact surface ``m`` (grid spacing ``h``, reference seconds ``t_ref``)."""
    first = runs[0]
    total = [r["time_sample_s"] + r["time_extract_s"] for r in runs]
    d = m["distances"]
    note = ""
    if m["distance_method"] == "lipschitz_bracket":
        note = ("distance to the surface: certified upper bound by a sign-change bracket; its error bound "
                "b − |φ|/L is reference_error_bound")
        if not math.isfinite(m["reference_error_bound"]):
            note += "; the declared Lipschitz bound is refuted (|φ|/L > a certified distance): no error bound"
    if first["faces"].shape[0] == 0:
        note = (note + "; " if note else "") + "φ has no sign change on the grid: empty mesh, infinite distance"
    common = {
        **base, "outcome": "ok", "reason": note,
        "error_p99": float(np.percentile(d, 99)) if d.size else math.inf,
        "error_median": float(np.median(d)) if d.size else math.inf,
        "n_checked": int(m["n_mesh_samples"] + m["n_surface_samples"]),
        "time_median_s": float(np.median(total)), "time_iqr_s": _iqr(total),
        "time_samples_s": json.dumps(total), "n_samples": len(total),
        "reference_error_bound": m["reference_error_bound"], "reference_s": t_ref,
        "timing_note": "φ sampling on the grid (numpy) + skimage marching_cubes, per repeat",
        "resolution": n, "grid_spacing": h,
        "n_vertices": int(first["vertices"].shape[0]), "n_faces": int(first["faces"].shape[0]),
        "time_sample_s": float(np.median([r["time_sample_s"] for r in runs])),
        "time_extract_s": float(np.median([r["time_extract_s"] for r in runs])),
        **{k: m[k] for k in ("hausdorff", "chamfer", "hausdorff_mesh_to_surface", "hausdorff_surface_to_mesh",
                             "chamfer_mesh_to_surface", "chamfer_surface_to_mesh", "n_mesh_samples",
                             "n_surface_samples", "covering_mesh", "covering_surface",
                             "surface_cover_certified", "distance_method")},
    }
    return common


def _ok(df: pd.DataFrame) -> pd.DataFrame:
    if df is None or not len(df):
        return pd.DataFrame()
    d = df[(df.get("family") == FAMILY)] if "family" in df else df
    return d


def summary_table(df: pd.DataFrame) -> pd.DataFrame:
    """Wide: one row per (case, resolution) with Hausdorff, Chamfer, time, mesh size; skipped and
    failed cases listed with their reason."""
    d = _ok(df)
    if not len(d):
        return pd.DataFrame()
    rows = []
    for (case, knob), g in d.groupby(["case_id", "knob"], sort=False):
        r0 = g.iloc[0]
        by = {str(r["quantity"]): r for _, r in g.iterrows()}
        if r0["outcome"] != "ok":
            rows.append({"case": case, "N": "—", "outcome": r0["outcome"], "reason": str(r0.get("reason", ""))[:120]})
            continue
        rows.append({"case": case, "N": int(r0["resolution"]), "outcome": "ok",
                     "hausdorff": by["hausdorff"]["error_max"] if "hausdorff" in by else math.nan,
                     "chamfer": by["chamfer"]["error_max"] if "chamfer" in by else math.nan,
                     "time_s": r0["time_median_s"], "sample_s": r0["time_sample_s"], "mc_s": r0["time_extract_s"],
                     "faces": int(r0["n_faces"]), "h": r0["grid_spacing"],
                     "rho": max(r0["covering_mesh"], r0["covering_surface"]),
                     "ref_bound": r0["reference_error_bound"], "reason": str(r0.get("reason", "") or "")[:120]})
    return pd.DataFrame(rows)


def hausdorff_rates(df: pd.DataFrame) -> pd.DataFrame:
    """Per case, the least-squares slope of log H against log h over the ok resolutions with
    finite H (2 for a smooth surface extracted by marching cubes)."""
    d = _ok(df)
    out = []
    if not len(d):
        return pd.DataFrame(columns=["case", "slope", "n"])
    d = d[(d["outcome"] == "ok") & (d["quantity"] == "hausdorff")]
    for case, g in d.groupby("case_id", sort=False):
        e, h = g["error_max"].astype(float).to_numpy(), g["grid_spacing"].astype(float).to_numpy()
        m = np.isfinite(e) & (e > 0)
        slope = float(np.polyfit(np.log(h[m]), np.log(e[m]), 1)[0]) if m.sum() >= 2 else math.nan
        out.append({"case": case, "slope": slope, "n": int(m.sum())})
    return pd.DataFrame(out)


def markdown_section(df: pd.DataFrame, image: str | None = None) -> str:
    """The report's "Surface extraction" section (markdown): what is measured, the table of
    :func:`summary_table`, the convergence slopes, and ``image`` (a path relative to the report)
    if given."""
    t = summary_table(df)
    lines = ["## Surface extraction (marching cubes)", "",
             "φ sampled with numpy on an N³ grid over the scene's bounding cube (padded by one cell), "
             "`skimage.measure.marching_cubes` at level 0. Scored in float64 against the exact surface: "
             "Hausdorff = max of the two directed maxima, Chamfer = mean of the two directed means "
             "(unsquared; area-weighted on the mesh). Sampled on a level-3 barycentric grid per mesh face and "
             "on the exact surface with covering radius ≤ h/2: the sampled Hausdorff is a lower bound of the "
             "true one, by at most ρ (column `rho`). Time: sampling + extraction, median of repeats.", ""]
    if not len(t):
        return "\n".join(lines + ["No extraction rows in this run.", ""])
    if image:
        lines += [f"![time vs Hausdorff]({image})", ""]
    ok = t[t["outcome"] == "ok"]
    if len(ok):
        fmt = ok.copy()
        for c in ("hausdorff", "chamfer", "time_s", "sample_s", "mc_s", "h", "rho", "ref_bound"):
            fmt[c] = [("∞" if v == math.inf else f"{v:.3g}") if isinstance(v, (float, int)) and not pd.isna(v)
                      else "—" for v in fmt[c]]
        lines += [_md_table(fmt.drop(columns=["outcome"]))]
        rates = hausdorff_rates(df)
        if len(rates):
            lines += ["", "Hausdorff order in h (least-squares slope of log H vs log h; 2 expected for smooth "
                      "surfaces): " + ", ".join(f"{r.case} {r.slope:.2f}" for r in rates.itertuples()
                                                if not math.isnan(r.slope)), ""]
    other = t[t["outcome"] != "ok"]
    if len(other):
        lines += ["", "Not run:", ""] + [f"- {r.case}: {r.outcome} — {r.reason}" for r in other.itertuples()]
    return "\n".join(lines) + "\n"


def _md_table(d: pd.DataFrame) -> str:
    cols = list(d.columns)
    out = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for _, r in d.iterrows():
        out.append("| " + " | ".join(str(r[c]).replace("|", "\\|") for c in cols) + " |")
    return "\n".join(out)


def plot(df: pd.DataFrame, path) -> Path | None:
    """Time (s) against Hausdorff distance per case, log-log, one line per case through its
    resolutions (annotated with N).  Writes ``path`` (png); None when there is nothing to plot."""
    d = _ok(df)
    if not len(d):
        return None
    d = d[(d["outcome"] == "ok") & (d["quantity"] == "hausdorff")]
    d = d[np.isfinite(d["error_max"].astype(float)) & (d["error_max"].astype(float) > 0)]
    if not len(d):
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 5))
    for case, g in d.groupby("case_id", sort=True):
        g = g.sort_values("resolution")
        ax.plot(g["error_max"].astype(float), g["time_median_s"].astype(float), "o-", label=case, ms=4)
        for _, r in g.iterrows():
            ax.annotate(str(int(r["resolution"])), (float(r["error_max"]), float(r["time_median_s"])),
                        fontsize=6, xytext=(2, 2), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("Hausdorff distance to the exact surface")
    ax.set_ylabel("time: φ sampling + marching cubes (s, median)")
    ax.set_title("marching cubes: time vs error (labels: N)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=6, loc="best")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)
    return path


__all__ = ["FAMILY", "METHOD", "QUANTITIES", "applies", "default_cases", "extract", "grid_box", "hausdorff_rates",
           "markdown_section", "plot", "run_extraction", "summary_table"]
