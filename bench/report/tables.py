"""The report's tables, computed from a run's rows: best accuracy, fastest to an error target,
configurations by outcome, the support matrix, what did not run, convergence rates, the claims
ledger, the stability cells and how the run was spread."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from . import summary

_ok = summary.ok_rows
TARGETS = summary.TARGETS


CONFIG_KEY = ["case_id", "backend", "dtype", "method", "knob"]


def summary_table(df: pd.DataFrame) -> pd.DataFrame:
    """Per case × method × quantity × dtype × backend: the most accurate setting, its time and cost."""
    ok = _ok(df)
    rows = []
    for (cid, method, q, dtype, bid), g in ok.groupby(["case_id", "method", "quantity", "dtype", "backend"]):
        best = g.sort_values(["error_max", "time_median_s"]).iloc[0]
        rows.append({
            "case": cid, "method": method, "quantity": q, "dtype": dtype, "backend": bid,
            "best max error": error_text(best), "at knob": knob_label(method, best["knob"]),
            "time median [ms]": 1e3 * best["time_median_s"], "time IQR [ms]": 1e3 * best["time_iqr_s"],
            "× closed form": best["time_ratio_cf"], "compile [s]": best["compile_s"],
            "kernel": _kernel(best.get("compile_cache")),
            "evals/ray mean": best["evals_per_ray"], "p99": best.get("evals_p99"), "max": best.get("evals_max"),
            "ray statuses": _statuses(best.get("status_counts")),
        })
    return pd.DataFrame(rows)


def error_text(row) -> str:
    """A row's max error as the best-accuracy table says it: the number (3 significant digits), or
    why there is none.  An infinite error is a wrong or missing answer the max cannot hide (a false
    hit or miss, a CONVERGED ray with a non-finite depth, a hitting ray the method flagged:
    bench/run/metrics.py), and says which and how many; no error at all (NaN) is a row with no
    ray checked: every hit declined (dt_unrolled's budget spent on every hit: MAX_ITER), or no ray
    answered (a surface render whose every ray is UNCERTIFIED).  An infinite error also gives the
    largest finite one, over the rays answered (``error_max_finite``), and either says how many
    rays the reference flags (``n_not_judged``), which no error covers."""
    def count(column: str) -> int:  # (absent or NaN where the row's family has no such count)
        x = row.get(column)
        return int(x) if isinstance(x, (int, float, np.number)) and np.isfinite(x) else 0

    # rays the reference flags (no certified answer there: a declared Lipschitz bound it saw to be
    # false, a near-tangent ray) are left out of every error: the number must say so, or it reads
    # as the error over every ray
    unjudged = count("n_not_judged")
    unjudged = f" ({unjudged} ray(s) not judged: the reference flags them)" if unjudged else ""
    v = float(row.get("error_max", np.nan))
    if np.isfinite(v):
        return f"{v:.3g}{unjudged}"

    if np.isnan(v):
        declined = count("n_declined")
        return f"none: no ray answered ({declined} declined)" if declined else "none: no ray checked (see its statuses)"
    flagged = count("n_miss_declined")
    parts = [f"{k} {what}" for k, what in ((count("n_false_hit"), "false hit(s)"),
                                           (count("n_false_miss") - flagged, "silent miss(es)"),
                                           (count("n_converged_nonfinite"), "CONVERGED non-finite"),
                                           (flagged, "hitting ray(s) flagged")) if k > 0]
    # the error of the answers it did give: a wrong CONVERGED depth must not read like a correct one
    # beside the same count of flagged rays
    rest = float(row.get("error_max_finite", np.nan))
    rest = f"; {rest:.3g} on the rest" if np.isfinite(rest) else ""
    return (f"inf: {', '.join(parts)}" if parts else "inf") + rest + unjudged


def _kernel(cache) -> str:
    """A row's ``compile_cache`` as the report says it: compiled (cold), reused (warm) or ""."""
    return {"compiled": "compiled (cold)", "reused": "reused (warm)"}.get(cache, "") if isinstance(cache, str) else ""


def compile_table(df: pd.DataFrame) -> pd.DataFrame:
    """Per backend, compile time split by whether the kernel was compiled in this run (cold) or
    reused (warm: from the persistent cache or from a kernel this run compiled before;
    ``compile_cache``); configurations whose backend does not say are "not stated"."""
    ok = _ok(df).drop_duplicates(["case_id", "method", "dtype", "backend", "knob"])
    if not len(ok) or "compile_s" not in ok:
        return pd.DataFrame()
    kernel = ok["compile_cache"] if "compile_cache" in ok else pd.Series("", index=ok.index)
    ok = ok.assign(kernel=[_kernel(c) or "not stated" for c in kernel],
                   compile_s=pd.to_numeric(ok["compile_s"], errors="coerce"))
    g = ok.groupby(["backend", "kernel"])["compile_s"]
    return pd.DataFrame({"configurations": g.size(), "compile total [s]": g.sum(), "median [s]": g.median(),
                         "max [s]": g.max()}).reset_index()


knob_label = summary.knob_label


_statuses = summary.status_text


def fastest_to_target(df: pd.DataFrame, targets=TARGETS) -> pd.DataFrame:
    """Per case × method × quantity × dtype × backend and error target: the fastest knob setting
    whose max error is ≤ the target (``time ms @ knob``), or ``not reached``."""
    ok = _ok(df)
    rows = []
    # numpy per group, not a pandas filter and sort per target: a quick run's 1,600 of those were
    # 3.5 of its report's 8.8 s besides the figures
    for (cid, method, q, dtype, bid), g in ok.groupby(["case_id", "method", "quantity", "dtype", "backend"]):
        row = {"case": cid, "method": method, "quantity": q, "dtype": dtype, "backend": bid}
        err, t = g["error_max"].to_numpy(float), g["time_median_s"].to_numpy(float)
        ratio, knobs = g["time_ratio_cf"].to_numpy(float), g["knob"].to_numpy()
        for tgt in targets:
            within = np.flatnonzero(err <= tgt)
            if not within.size:
                row[f"≤ {tgt:.0e}"] = "not reached"
                continue
            j = within[np.argsort(t[within], kind="stable")[0]]  # the fastest (NaN times last)
            knob = knob_label(method, knobs[j])  # "" for a method without knobs: no "@"
            row[f"≤ {tgt:.0e}"] = f"{1e3 * t[j]:.3g} ms (×{ratio[j]:.3g})" + (f" @ {knob}" if knob else "")
        rows.append(row)
    return pd.DataFrame(rows)


def config_outcomes(df: pd.DataFrame) -> pd.DataFrame:
    """One row per configuration: ``ran`` if any quantity was measured, else ``failed`` if it
    failed, else ``skipped``; with the first reason."""
    rank = df["outcome"].map({"ok": 0, "failed": 1, "skipped": 2}).fillna(3)
    d = df.assign(_rank=rank).sort_values("_rank")
    first = d.groupby(CONFIG_KEY, sort=False).first().reset_index()
    return first[CONFIG_KEY + ["outcome", "reason"]]


def support_matrix(df: pd.DataFrame) -> pd.DataFrame:
    """backend × method: configurations ran / skipped / failed, as one readable cell each."""
    c = config_outcomes(df)
    t = c.groupby(["backend", "method", "outcome"]).size().unstack(fill_value=0)
    for col in ("ok", "skipped", "failed"):
        if col not in t.columns:
            t[col] = 0

    def cell(r) -> str:
        parts = [f"ran {r['ok']}"] if r["ok"] else []
        parts += [f"skipped {r['skipped']}"] if r["skipped"] else []
        parts += [f"FAILED {r['failed']}"] if r["failed"] else []
        return " · ".join(parts) or "—"

    cells = t.apply(cell, axis=1).rename("cell").reset_index()
    out = cells.pivot(index="backend", columns="method", values="cell").fillna("not planned").reset_index()
    out.columns.name = None
    return out


def not_run(df: pd.DataFrame) -> pd.DataFrame:
    """Skipped or failed rows grouped by reason (quantities a method could not be checked on
    included), so nothing disappears silently."""
    bad = df[df["outcome"] != "ok"].copy()
    if bad.empty:
        return pd.DataFrame(columns=["outcome", "backend", "method", "quantity", "reason", "rows"])
    bad["reason"] = bad["reason"].fillna("").astype(str).str.slice(0, 300)
    return (bad.groupby(["outcome", "backend", "method", "quantity", "reason"], dropna=False).size()
            .rename("rows").reset_index())


def rates_table(all_series: list[tuple[str, list[dict]]]) -> pd.DataFrame:
    rows = []
    for key, series in all_series:
        for s in series:
            rows.append({"plot": key, "method": s["method"], "backend": s["backend"], "knob": s["knob"],
                         "fixed knobs": s["fixed"], "fitted rate p (error ∝ knob^−p)": s["rate"],
                         "error at largest knob": s["error"][-1]})
    return pd.DataFrame(rows)


def read_claims(run_dir: Path) -> pd.DataFrame | None:
    p = Path(run_dir) / "claims.csv"
    if not p.exists():
        return None
    return pd.read_csv(p, keep_default_na=False)


CLAIM_COLUMNS = ["id", "statement", "equation", "scope", "how_checked", "verdict", "key_numbers", "plot"]


#: verdict order of the ledger tables: what a reader must see first comes first
VERDICT_ORDER = {"fails": 0, "error": 1, "holds under conditions": 2, "holds": 3}


def claims_in_reading_order(claims: pd.DataFrame) -> pd.DataFrame:
    """Failures first, then errors, conditional holds and holds; catalogue order within each."""
    rank = claims["verdict"].map(VERDICT_ORDER).fillna(1) if "verdict" in claims else 0
    return claims.assign(_rank=rank).sort_values("_rank", kind="stable").drop(columns="_rank")


STABILITY_DIR = "stability"


def spread_section(df: pd.DataFrame, env: dict) -> tuple[list[str], pd.DataFrame]:
    """Lines and the per-worker table of "How the run was spread" (:mod:`bench.report.spread`); none for
    a results set without configurations.  Never raises (a section, not a reason to lose the report)."""
    from . import spread

    try:
        if not len(df) or "task_s" not in df:
            return [], pd.DataFrame()
        s = spread.summary(df, env)
        lines = [f"{s['cluster']}: {s['configurations']} configurations on {s['processes that ran configurations']} "
                 f"process(es), at most {s['workers at once']} at once; machine keys: "
                 f"{'; '.join(s['machine keys']) or 'not recorded'}",
                 f"wall {s['wall s']:.1f} s for the configurations; task times sum to {s['task s (sum)']:.1f} s"
                 + (f" plus {s['reference tasks']} shared reference task(s), {s['reference task s (sum)']:.1f} s"
                    if s["reference tasks"] else "")
                 + (f"; parallel efficiency {s['parallel efficiency']:.0%}" if np.isfinite(s["parallel efficiency"])
                    else "")]
        if np.isfinite(s["overhead s per task (mean)"]):
            lines.append(f"per-task overhead (latency seen by the client − time on the worker): mean "
                         f"{s['overhead s per task (mean)'] * 1e3:.1f} ms, median "
                         f"{s['overhead s per task (median)'] * 1e3:.1f} ms; central cost "
                         f"{s['central s per task'] * 1e3:.2f} ms per task; workers that died: {s['workers died']}; "
                         f"configurations that killed their worker: {s['killed-worker failures']}")
        proj, _ = spread.project(df, env, workers=(64,))
        if len(proj):
            r = proj.iloc[0]
            lines.append(f"projected on 64 such workers: {r['projected wall s']:.1f} s (limited by {r['limited by']}; "
                         "`python -m bench spread RUN_DIR` gives the model and its assumptions)")
        if s["configurations without task time"]:
            lines.append(f"{s['configurations without task time']} configurations have no recorded task time")
        return lines, spread.per_worker(df)
    except Exception as exc:  # noqa: BLE001
        return [f"(unavailable: {type(exc).__name__}: {exc})"], pd.DataFrame()


def _default_knobs(df: pd.DataFrame) -> pd.DataFrame:
    """Rows at the method's default knobs (the stability matrix judges methods as shipped)."""
    if not len(df):
        return df
    keep = [knob_label(str(m), str(k)) in ("defaults", "") for m, k in zip(df["method"], df["knob"].fillna(""))]
    return df[np.array(keep, bool)]


def stability_section(df: pd.DataFrame, run_dir: Path) -> tuple[pd.DataFrame, str]:
    """The stability cells of a run and a note saying where they come from: the stability stage
    (``run_dir/stability/results.*``, written by ``bench run`` for a suite with a stability plan)
    when present, else the run's own root-finder rows on adversarial cases; default knobs only."""
    from ..studies import stability
    from ..run.results import read_results

    note = "from the run's own rows on adversarial cases"
    src = df
    stage = Path(run_dir) / STABILITY_DIR
    if (stage / "results.parquet").exists() or (stage / "results.csv").exists():
        try:
            src = read_results(stage)
            note = f"from the stability stage ({STABILITY_DIR}/results.*)"
        except Exception as exc:  # an unreadable stage is a note in the report, not a lost report
            note = f"the stability stage could not be read ({type(exc).__name__}: {exc}); from the run's own rows"
    if src is None or not len(src) or "method" not in src:
        return stability.stability_cells(None), note
    return stability.stability_cells(_default_knobs(src)), note

