"""The stability matrix: every root finder × backend × dtype against each adversarial ray family.

Rows of a results table (``family == "root"``, quantity ``depth``) on cases that belong to an
adversarial family (:data:`reference.cases.ADVERSARIAL_FAMILIES`: a case's family is the first
of those among its tags) are grouped into one *cell* per (method, backend, dtype, family).  A
cell holds the largest depth error of the rays the method called CONVERGED, false hits, silent
false misses, the rays it flagged, the worst evaluations and iterations per ray and the merged
status histogram, and one verdict:

* **survived** (✓) — no wrong answer and no flagged ray: no false hit, no hitting ray reported
  MISS, no CONVERGED ray with a non-finite t, and every CONVERGED ray within the depth tolerance
  ``tol = min(√ε(dtype) · max(1, T) + 100 ε(dtype) · R, S/4)`` (T the largest exact depth of the case: the
  error scales with the depth's magnitude; R the largest norm of a hitting ray's origin).  √ε is
  the accuracy a certified answer reaches at a double root (the tangent family): |φ| at rounding
  level ε moves a double root by O(√ε).  float64: 1.5e-8 · T, float32: 3.5e-4 · T.  The second
  term is the rounding of the points a depth is computed from: o + t·d rounds by ε(|o| + |t|), and
  the certified methods resolve a crossing to a few of their rounding model's 8ε(|t| + |o|₁ + |c|
  + r) (docs/methods.md, "Precision").  In the catalog it is negligible (R ≈ T), but a scene far
  from the origin of its frame, seen from close by, has small depths and large coordinates: a
  unit sphere at (1e4, 0, 0) seen from 3 units has T ≈ 2.7 while float32 places its points only
  to 1e-3 (R = 1e4: 0.12 allowed).  The tolerance is capped at a quarter of the scene's size S
  (the diameter of its bounding ball): far from the origin in float32 the two terms grow past the
  scene itself (357 for the unit sphere 1e6 away), and an answer on its far side would count.
* **flagged** (⚑) — no wrong answer, but some rays carry a failure status (anything other than
  CONVERGED and MISS: MAX_ITER, NON_FINITE, BAD_INPUT, ILL_CONDITIONED, LIPSCHITZ_VIOLATED,
  UNCERTIFIED).  A flagged ray says "I could not answer", which is not a silent wrong answer: a
  flagged cell *counts as survived* on the scoreboard (no silent wrong answer).  The
  constant-step marchers do not see a feature crossed twice within their step; their samples'
  spheres certify what they report (``impls.core.rootfind.ConstantStep``), so such a feature
  flags their rays, as the report's legend states.
* **failed** (✗) — a silent wrong answer (a false hit, a false miss reported as MISS, a
  CONVERGED ray over the tolerance or with a non-finite t), or the configuration failed.
* **n/a** (—) — every configuration of the cell was skipped (with its reason).
* **not judged** (?) — the configurations ran, but the reference flags every ray of the cell's
  cases (no certified answer: e.g. exact tangent rays, where float64 cannot tell a touch from a
  near miss; ``n_not_judged``, :func:`bench.run.metrics.judged_rays`).  Like n/a it is left out of the
  scoreboard.  Where only some rays are flagged the cell is judged on the others and counts the
  rest in ``n_not_judged``.

``bench.run.metrics`` counts in ``n_false_miss`` every hitting ray that is not CONVERGED, flagged
ones included, and sets ``error_max`` = inf for them; the silent false misses are
``n_false_miss − n_miss_declined`` (rows without ``n_miss_declined``, from older runs, count every
false miss as silent), and the CONVERGED error is ``error_max_finite``.

All functions are pure (frames in, frames out); the case catalog is consulted only through the
``family_of`` and ``scale_of`` arguments' defaults.
"""

from __future__ import annotations

import functools
import json
import math

import numpy as np
import pandas as pd

#: statuses that are answers (a hit, or no surface); every other status flags a ray
ANSWER_STATUSES = ("CONVERGED", "MISS")
MARKS = {"survived": "✓", "flagged": "⚑", "failed": "✗", "n/a": "—", "not judged": "?"}
#: the cell key
CELL_KEY = ["method", "backend", "dtype", "family"]


def families() -> tuple[str, ...]:
    """The matrix's columns, in the catalog's order (most specific family first)."""
    from reference.cases import ADVERSARIAL_FAMILIES

    return ADVERSARIAL_FAMILIES


@functools.cache
def catalog_family(case_id: str) -> str | None:
    """The adversarial family of a catalog case, None for an unknown id or a case of none."""
    from reference.cases import adversarial_family, tags_of

    try:
        return adversarial_family(tags_of(case_id))
    except KeyError:
        return None


@functools.cache
def catalog_scale(case_id: str) -> float:
    """T: the largest finite |exact depth| of a catalog case (1 for an unknown id or no hit)."""
    from reference.cases import get_case

    try:
        t = np.asarray(get_case(case_id).exact_t, np.float64)
    except KeyError:
        return 1.0
    t = np.abs(t[np.isfinite(t)])
    return float(t.max()) if t.size else 1.0


@functools.cache
def catalog_origin_norm(case_id: str) -> float:
    """R: the largest norm ‖o‖ of a hitting ray's origin in a catalog case (0 for an unknown id
    or no hit)."""
    from reference.cases import get_case

    try:
        case = get_case(case_id)
    except KeyError:
        return 0.0
    hit = np.isfinite(np.asarray(case.exact_t, np.float64))
    return float(np.linalg.norm(np.asarray(case.origins, np.float64)[hit], axis=1).max()) if hit.any() else 0.0


#: roundings ε·‖o‖ of the origins' magnitude a CONVERGED depth may be off (module docstring)
ORIGIN_ROUNDINGS = 100.0


@functools.cache
def catalog_size(case_id: str) -> float:
    """S: the diameter of a catalog case's scene's bounding ball (inf for an unknown id or a scene
    without one)."""
    from reference.cases import get_case

    try:
        _, r = get_case(case_id).scene.bounding_sphere()
        return 2.0 * float(r) if math.isfinite(float(r)) and float(r) > 0 else math.inf
    except Exception:  # noqa: BLE001 - no ball: no cap
        return math.inf


#: the largest depth error counted right, as a share of the scene's size (:func:`depth_tolerance`)
SIZE_SHARE = 0.25


def depth_tolerance(dtype: str, scale: float, origin_norm: float = 0.0, size: float = math.inf) -> float:
    """``min(√ε(dtype) · max(1, scale) + 100 ε(dtype) · origin_norm, size / 4)``: the largest depth
    error of a CONVERGED ray that still counts as right (module docstring).  The cap: on
    ``sphere.far.1e6`` in float32 the two terms allow 357 for a sphere of diameter 2, so an answer
    on its far side counted as right (probe of 2026-11-30); an error of a quarter of the scene is
    wrong whatever the dtype resolves there."""
    eps = float(np.finfo(np.dtype(dtype)).eps)
    tol = math.sqrt(eps) * max(1.0, abs(float(scale))) + ORIGIN_ROUNDINGS * eps * abs(float(origin_norm))
    return min(tol, SIZE_SHARE * float(size))


def _num(v, default=0.0) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return default
    return default if math.isnan(f) else f


def status_histogram(v) -> dict[str, int]:
    """A row's ``status_counts`` (JSON, or a dict) as {status name: rays}; {} where it has none."""
    if isinstance(v, dict):
        return {str(k): int(n) for k, n in v.items()}
    if not isinstance(v, str) or not v:
        return {}
    try:
        return {str(k): int(n) for k, n in json.loads(v).items()}
    except (ValueError, AttributeError, TypeError):
        return {}


def judge_cell(rows, dtype: str, scale_of=catalog_scale, origin_of=catalog_origin_norm, size_of=catalog_size) -> dict:
    """The verdict and numbers of one cell from its result rows (any number of cases): a frame,
    or its rows as dicts (``DataFrame.to_dict("records")``, which :func:`stability_cells` makes
    once for all cells: per cell it costs more than the judging)."""
    rows = rows.to_dict("records") if isinstance(rows, pd.DataFrame) else list(rows)
    out = {"verdict": "n/a", "error_max": float("nan"), "tolerance": float("nan"), "n_false_hit": 0,
           "n_false_miss": 0, "n_flagged": 0, "n_nonfinite": 0, "n_over_tol": 0, "n_not_judged": 0,
           "evals_max": float("nan"),
           "iterations_max": float("nan"), "statuses": {}, "cases": sorted({str(r["case_id"]) for r in rows}),
           "reasons": []}
    failed, errs, ok_rows, judged_rows = False, [], 0, 0
    statuses: dict[str, int] = {}
    for r in rows:
        outcome = str(r.get("outcome", ""))
        if outcome == "failed":
            failed = True
            out["reasons"].append(f"{r['case_id']}: configuration failed: {str(r.get('reason', ''))[:200]}")
            continue
        if outcome != "ok":
            out["reasons"].append(f"{r['case_id']}: skipped: {str(r.get('reason', ''))[:200]}")
            continue
        ok_rows += 1
        n_nj = int(_num(r.get("n_not_judged")))
        out["n_not_judged"] += n_nj
        if n_nj and int(_num(r.get("n_checked"))) == 0:  # the reference flags every ray: nothing to judge
            out["reasons"].append(f"{r['case_id']}: not judged: the reference flags all {n_nj} rays")
            continue
        judged_rows += 1
        cid = str(r["case_id"])
        tol = depth_tolerance(dtype, scale_of(cid), origin_of(cid), size_of(cid))
        out["tolerance"] = tol if math.isnan(out["tolerance"]) else max(out["tolerance"], tol)
        st = status_histogram(r.get("status_counts"))
        for k, n in st.items():
            statuses[k] = statuses.get(k, 0) + n
        flagged = sum(n for k, n in st.items() if k not in ANSWER_STATUSES)
        n_fh = int(_num(r.get("n_false_hit")))
        declined = r.get("n_miss_declined")
        n_fm = int(_num(r.get("n_false_miss"))) - int(_num(declined))  # silent: reported MISS
        err = _num(r.get("error_max_finite"), float("nan"))
        n_nf = int(_num(r.get("n_converged_nonfinite")))
        if "n_converged_nonfinite" not in r or pd.isna(r.get("n_converged_nonfinite")):
            # older rows: an infinite max error that no false hit or miss explains is a CONVERGED NaN
            n_nf = int(_num(r.get("error_max"), 0.0) == math.inf and n_fh + int(_num(r.get("n_false_miss"))) == 0)
        over = int(not math.isnan(err) and err > tol)
        out["n_false_hit"] += n_fh
        out["n_false_miss"] += max(n_fm, 0)
        out["n_flagged"] += flagged
        out["n_nonfinite"] += n_nf
        out["n_over_tol"] += over
        if not math.isnan(err) and st.get("CONVERGED", 0):  # else it is 0 from rays both call a miss
            errs.append(err)
        for col in ("evals_max", "iterations_max"):
            v = _num(r.get(col), float("nan"))
            if not math.isnan(v):
                out[col] = v if math.isnan(out[col]) else max(out[col], v)
        if n_fh or n_fm > 0 or n_nf or over:
            out["reasons"].append(
                f"{r['case_id']}: " + ", ".join(s for s in (
                    f"{n_fh} false hit(s)" if n_fh else "", f"{n_fm} hitting ray(s) reported MISS" if n_fm > 0 else "",
                    f"{n_nf} CONVERGED with non-finite t" if n_nf else "",
                    f"CONVERGED error {err:.3g} > tolerance {tol:.3g}" if over else "") if s))
    out["statuses"] = statuses
    out["error_max"] = max(errs) if errs else float("nan")
    wrong = out["n_false_hit"] or out["n_false_miss"] or out["n_nonfinite"] or out["n_over_tol"]
    if failed or wrong:
        out["verdict"] = "failed"
    elif judged_rows:
        out["verdict"] = "flagged" if out["n_flagged"] else "survived"
    elif ok_rows:
        out["verdict"] = "not judged"
    return out


def stability_cells(df: pd.DataFrame, family_of=catalog_family, scale_of=catalog_scale) -> pd.DataFrame:
    """One row per (method, backend, dtype, family) with :func:`judge_cell`'s columns; only
    root-finder depth rows (and their failed/skipped configuration rows) on adversarial cases."""
    cols = CELL_KEY + ["verdict", "mark", "error_max", "tolerance", "n_false_hit", "n_false_miss", "n_flagged",
                       "n_nonfinite", "n_over_tol", "n_not_judged", "evals_max", "iterations_max", "statuses", "cases", "reasons"]
    if df is None or not len(df):
        return pd.DataFrame(columns=cols)
    d = df.copy()
    fam = d["family"].fillna("").astype(str) if "family" in d else pd.Series("", index=d.index)
    q = d["quantity"].fillna("").astype(str) if "quantity" in d else pd.Series("depth", index=d.index)
    d = d[(fam == "root") & q.isin(["depth", ""])]
    if not len(d):
        return pd.DataFrame(columns=cols)
    fams = {c: family_of(c) for c in set(map(str, d["case_id"]))}  # once per case: a catalog look-up each
    d = d.assign(adv_family=[fams[str(c)] for c in d["case_id"]])
    d = d[d["adv_family"].notna()]
    groups: dict[tuple, list[dict]] = {}
    for r in d.to_dict("records"):  # once: a frame's rows as dicts per cell cost more than judging them
        if any(pd.isna(r[k]) for k in ("method", "backend", "dtype")):
            continue  # as groupby drops a missing key
        groups.setdefault((r["method"], r["backend"], r["dtype"], r["adv_family"]), []).append(r)
    rows = []
    for (method, backend, dtype, family), g in sorted(groups.items(), key=lambda kv: tuple(map(str, kv[0]))):
        cell = judge_cell(g, str(dtype), scale_of)
        rows.append({"method": method, "backend": backend, "dtype": dtype, "family": family,
                     "mark": MARKS[cell["verdict"]], **cell})
    return pd.DataFrame(rows, columns=cols)


def survived(verdict: str) -> bool:
    """Flagged counts as survived: the method said it could not answer, it did not answer wrongly."""
    return verdict in ("survived", "flagged")


def scoreboard(cells: pd.DataFrame) -> pd.DataFrame:
    """Per backend and dtype: families survived (every root finder's cell of the family on that
    backend in that dtype survived or flagged) out of the families it has a judged cell in, and
    the same in cells; the families failed, by name.  (Per dtype, so that float32's precision
    floor does not hide how float64 fares.)"""
    cols = ["backend", "dtypes", "families_survived", "families_total", "cells_survived", "cells_flagged",
            "cells_total", "failed_families"]
    if cells is None or not len(cells):
        return pd.DataFrame(columns=cols)
    order = {f: i for i, f in enumerate(families())}
    rows = []
    for (backend, dtype), g in cells.groupby(["backend", "dtype"], sort=False):
        judged = g[~g["verdict"].isin(["n/a", "not judged"])]
        fam_ok = judged.groupby("family")["verdict"].agg(lambda v: all(survived(x) for x in v))
        failed = sorted((f for f, ok in fam_ok.items() if not ok), key=lambda f: (order.get(f, len(order)), f))
        rows.append({"backend": backend, "dtypes": [str(dtype)],
                     "families_survived": sum(bool(v) for v in fam_ok.values), "families_total": int(len(fam_ok)),
                     "cells_survived": sum(survived(v) for v in judged["verdict"]),
                     "cells_flagged": int((judged["verdict"] == "flagged").sum()),
                     "cells_total": int(len(judged)), "failed_families": failed})
    return pd.DataFrame(rows, columns=cols)


def scoreboard_lines(board: pd.DataFrame) -> list[str]:
    """``numpy (float64, float32): 6/9 families survived (71/90 cells, 4 of them flagged); failed:
    understated, tangent, far``."""
    out = []
    for _, r in board.sort_values(["dtypes", "backend"], key=lambda c: c.astype(str), ascending=[False, True]).iterrows():
        if not r["families_total"]:  # "0/0 families survived" would read as a verdict
            out.append(f"{r['backend']} ({', '.join(r['dtypes'])}): no judged cell (every adversarial case of the plan "
                       "skipped on it: declined or not implemented)")
            continue
        line = (f"{r['backend']} ({', '.join(r['dtypes'])}): {r['families_survived']}/{r['families_total']} "
                f"families survived "
                f"({r['cells_survived']}/{r['cells_total']} cells, {r['cells_flagged']} of them flagged)")
        if r["failed_families"]:
            line += "; failed: " + ", ".join(r["failed_families"])
        out.append(line)
    return out


def _fmt(v: float, fmt: str = ".1e") -> str:
    return "—" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, fmt)


def cell_text(c) -> str:
    """Compact: mark, max CONVERGED depth error (one digit; — when no ray converged), worst field
    evaluations per ray (``✓ 2e-16 · 41``)."""
    if c["verdict"] in ("n/a", "not judged"):
        return MARKS[c["verdict"]]
    ev = c["evals_max"]
    return f"{c['mark']} {_fmt(c['error_max'], '.0e')} · {'—' if math.isnan(ev) else int(ev)}"


def cell_detail(c) -> str:
    """Everything else of a cell, one line: false hits/misses, flagged rays, statuses, tolerance,
    cases, reasons."""
    st = " · ".join(f"{k} {n}" for k, n in sorted(c["statuses"].items(), key=lambda kv: -kv[1]))
    parts = [c["verdict"], f"false hits {c['n_false_hit']}", f"false misses (reported MISS) {c['n_false_miss']}",
             f"flagged rays {c['n_flagged']}", f"statuses {st or '—'}", f"tolerance {_fmt(c['tolerance'])}",
             f"max iterations {'—' if math.isnan(c['iterations_max']) else int(c['iterations_max'])}",
             "cases " + ", ".join(c["cases"])]
    return "; ".join(parts + list(c["reasons"]))


def stability_matrix(cells: pd.DataFrame, detail: bool = False) -> pd.DataFrame:
    """Wide: rows method × backend × dtype, one column per family present (catalog order), each
    cell :func:`cell_text` (``detail=True``: ``(text, detail)`` pairs for a renderer)."""
    if cells is None or not len(cells):
        return pd.DataFrame(columns=["method", "backend", "dtype"])
    present = [f for f in families() if f in set(cells["family"])]
    present += sorted(set(cells["family"]) - set(present))
    rows = []
    # backends side by side per method and dtype (float64 first): a backend that disagrees stands out
    keyed = cells.assign(_dt=[-np.finfo(np.dtype(str(d))).bits if d else 0 for d in cells["dtype"]])
    for (method, _, dtype, backend), g in keyed.groupby(["method", "_dt", "dtype", "backend"]):
        row = {"method": method, "backend": backend, "dtype": dtype}
        by = {r["family"]: r for _, r in g.iterrows()}
        for f in present:
            if f in by:
                row[f] = (cell_text(by[f]), cell_detail(by[f])) if detail else cell_text(by[f])
            else:
                row[f] = (MARKS["n/a"], "not planned") if detail else MARKS["n/a"]
        rows.append(row)
    return pd.DataFrame(rows, columns=["method", "backend", "dtype"] + present)


__all__ = ["ANSWER_STATUSES", "MARKS", "status_histogram", "cell_detail", "cell_text", "depth_tolerance", "judge_cell", "scoreboard",
           "scoreboard_lines", "stability_cells", "stability_matrix", "survived"]


# -- the stage -------------------------------------------------------------------------------


def _per_backend(table: dict, backend_id: str, default):
    """``table``'s entry for ``backend_id`` (``jax:cpu``), else for its library (``jax``), else ``default``."""
    return table.get(backend_id, table.get(backend_id.partition(":")[0], default))


def stage_dtypes(suite, backend_id: str) -> list[str]:
    """The dtypes a stability stage runs on ``backend_id`` (``Suite.backend_dtypes``, by id or
    library, else the suite's)."""
    return list(_per_backend(suite.backend_dtypes, backend_id, suite.dtypes))


def stage_methods(suite, backend_id: str) -> list[str] | None:
    """The methods a stability stage runs on ``backend_id`` (``Suite.backend_methods``, by id or
    library; None: the suite's)."""
    m = _per_backend(suite.backend_methods, backend_id, None)
    return None if m is None else list(m)


def run_stage(suite, backends: dict, out_dir, *, timeout_s: float = 120.0, resume: bool = False,
              progress=None, env_extra: dict | None = None, executor=None) -> pd.DataFrame:
    """Run ``suite`` (a stability plan) accuracy only into ``out_dir``, backend by backend with
    :func:`stage_dtypes` each (the runner's resume mode appends each backend's rows to the same
    run); returns the frame.  ``resume``: finish a stage ``out_dir`` already holds.  ``executor``:
    where the configurations run (:func:`bench.run.runner.run`'s; None: this process)."""
    from pathlib import Path

    from ..run.runner import run
    from ..run.timing import TimingPolicy

    out_dir = Path(out_dir)
    policy = TimingPolicy(min_repeats=1, min_time_s=0.0, timeout_s=timeout_s, accuracy_only=True)
    df = None
    for i, (bid, backend) in enumerate(backends.items()):
        again = (resume or i > 0) and (out_dir / "environment.json").exists()
        df = run(suite, {bid: backend}, out_dir, dtypes=stage_dtypes(suite, bid), methods=stage_methods(suite, bid),
                 policy=policy, progress=progress, resume=again, env_extra=env_extra, executor=executor)
    return df if df is not None else pd.DataFrame()
