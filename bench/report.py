"""Reports: ``report.md`` (plots as PNG files in ``plots/``) and a self-contained ``report.html``
(the same plots inlined as base64 PNG; no network, no scripts).

Sections, in reading order:

1. *Best accuracy per backend* — per case, method, quantity and backend: the knob setting with
   the smallest max error, its median time, IQR, time in units of the closed-form ray–sphere
   intersection of the same rays, compile time and evaluations per ray.
2. *Fastest configuration reaching an error target* (1e-4, 1e-8, 1e-12): per case, method,
   quantity and backend, the cheapest knob setting whose max error is at or below the target.
2b. *Stability matrix* (:mod:`bench.stability`): the scoreboard (per backend, adversarial
   families survived / total), then every root finder × backend × dtype against each
   adversarial ray family at default knobs, from the run's stability stage (``stability/``
   under the run directory) when it has one, else from the run's own rows.
3. *Time versus error*, one plot per method family × case × quantity × dtype: one curve per
   method and backend (a point per knob setting; x = median time per call over all rays of the
   case, y = max error over the rays, both log); ✕ at the top edge = infinite error (a false hit
   or miss, a silent NaN); the dashed step line is the Pareto front over every curve.
4. *Convergence*: error against an integer knob (step budget, iterations, samples), log-log,
   with the fitted rate p of error ∝ knob^(−p) (least squares on the finite, non-zero errors).
5. *Support matrix* (backend × method: configurations ran / skipped / failed) and the reasons.
6. *Claims ledger* when the run directory has ``claims.csv`` (plots inlined).
7. *How the run was spread* (:mod:`bench.spread`): processes or dask workers, machine keys,
   configurations and task seconds per worker, wall time, the sum of task times, and the
   projected wall time on 64 workers.
8. *Environment*.
"""

from __future__ import annotations

import base64
import html
import json
import re
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from . import summary  # noqa: E402
from .results import write_text  # noqa: E402

_MARKERS = "osD^v<>ph*"
_LINESTYLES = ["-", "--", ":", "-."]
TARGETS = summary.TARGETS
CONFIG_KEY = ["case_id", "backend", "dtype", "method", "knob"]


def pareto_front(times: np.ndarray, errors: np.ndarray) -> np.ndarray:
    """Indices of the points not dominated in (time, error), sorted by time."""
    order = np.lexsort((errors, times))
    front, best = [], np.inf
    for i in order:
        if errors[i] < best:
            front.append(i)
            best = errors[i]
    return np.array(front, dtype=int)


def fit_rate(x: np.ndarray, err: np.ndarray) -> float:
    """p in err ≈ c · x^(−p) by least squares on log err vs log x (x increasing), over finite
    errors > 0, stopping at the floor: the fit ends before the first step whose local slope
    −Δlog err/Δlog x falls below a quarter of the median of the slopes before it (or below 0.05),
    since points on a tolerance or rounding floor measure the floor, not the rate.  NaN when fewer
    than 3 distinct x remain."""
    x, err = np.asarray(x, float), np.asarray(err, float)
    m = np.isfinite(err) & (err > 0) & (x > 0)
    x, err = x[m], err[m]
    order = np.argsort(x, kind="stable")
    x, err = x[order], err[order]
    lx, le = np.log(x), np.log(err)
    keep = min(2, x.size)
    with np.errstate(divide="ignore", invalid="ignore"):
        slopes = -np.diff(le) / np.diff(lx)
    while keep < x.size:
        s = slopes[keep - 1]
        prev = slopes[: keep - 1]
        prev = prev[np.isfinite(prev)]
        if not np.isfinite(s) or s < 0.05 or (prev.size and s < 0.25 * np.median(prev)):
            break
        keep += 1
    x, le = lx[:keep], le[:keep]
    if np.unique(x).size < 3:
        return float("nan")
    return float(-np.polyfit(x, le, 1)[0])


_ok = summary.ok_rows


def _label_unit(g: pd.DataFrame) -> tuple[str, str]:
    q = str(g["quantity"].iloc[0]) if "quantity" in g else "depth"
    unit = str(g["unit"].iloc[0]) if "unit" in g and isinstance(g["unit"].iloc[0], str) else ""
    return q, unit


def plot_time_vs_error(df: pd.DataFrame, title: str):
    """One curve per (method, backend) of ``df`` (rows of one case × quantity × dtype).

    Colour = method, marker and line style = backend; with several methods the legend lists
    methods and backends apart (not every pair), and the figure grows with it, so many curves
    never squeeze the axes."""
    ok = _ok(df)
    n_methods, n_backends = ok["method"].nunique(), ok["backend"].nunique()
    entries = (n_methods + n_backends if n_methods > 1 else n_backends) + 2
    fig, ax = plt.subplots(figsize=(7.5, max(4.8, 0.17 * entries + 1.0)), dpi=100)
    q, unit = _label_unit(ok) if len(ok) else ("depth", "scene units")
    finite = ok["error_max"].replace([np.inf], np.nan).dropna()
    positive = finite[finite > 0]
    floor = positive.min() / 10 if len(positive) else 1e-16
    top = max(positive.max() * 10 if len(positive) else 1.0, 1.0)
    methods = sorted(ok["method"].unique())
    backends = sorted(ok["backend"].unique())
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    if len(methods) > len(colors):
        colors = [plt.get_cmap("tab20")(i % 20) for i in range(len(methods))]
    many = len(methods) > 1
    for (method, bid), g in sorted(ok.groupby(["method", "backend"]), key=lambda kv: kv[0]):
        err = g["error_max"].to_numpy(float)
        y = np.where(np.isfinite(err), np.maximum(err, floor), top)
        t = g["time_median_s"].to_numpy(float)
        mi, bi = methods.index(method), backends.index(bid)
        label = None if many else bid
        color = colors[mi % len(colors)] if many else colors[bi % len(colors)]
        marker = _MARKERS[bi % len(_MARKERS)]
        # every knob setting is a point; the line joins this curve's own Pareto front (the knob
        # settings worth using), so sweeps of different knobs do not zigzag across each other
        ax.scatter(t, y, marker=marker, s=22, color=color, alpha=0.55, zorder=3)
        fin = np.isfinite(err)
        if fin.any():
            f = pareto_front(t[fin], y[fin])
            ax.plot(t[fin][f], y[fin][f], marker=marker, ls=_LINESTYLES[bi % len(_LINESTYLES)], lw=1.3, ms=5,
                    color=color, label=label, zorder=4)
        else:
            ax.plot([], [], marker=marker, color=color, label=label)
        bad = ~fin
        if bad.any():
            ax.scatter(t[bad], y[bad], marker="x", s=50, color="k", zorder=5)
    if many:  # legend: methods by colour, then backends by marker and line style
        for mi, m in enumerate(methods):
            ax.plot([], [], color=colors[mi % len(colors)], lw=2, label=m)
        for bi, b in enumerate(backends):
            ax.plot([], [], color="0.3", marker=_MARKERS[bi % len(_MARKERS)], ls=_LINESTYLES[bi % len(_LINESTYLES)],
                    label=b)
    if len(ok) and not np.isfinite(ok["error_max"].to_numpy(float)).all():
        _mark_infinite(ax, top)
    if len(ok):
        err = ok["error_max"].to_numpy(float)
        fin = np.isfinite(err)
        if fin.any():
            t = ok["time_median_s"].to_numpy(float)[fin]
            e = np.maximum(err[fin], floor)
            f = pareto_front(t, e)
            ax.plot(t[f], e[f], ls="--", color="0.35", lw=1, label="Pareto front (all)", drawstyle="steps-post",
                    zorder=2)
    ax.set_xscale("log")
    return _finish(fig, ax, "median time per call, all rays of the case [s]", f"max {q} error over rays", unit, title)


def _finish(fig, ax, xlabel: str, ylabel: str, unit: str, title: str):
    """Log y axis, labels with units, grid, the legend outside the axes (never over the data)."""
    ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(f"{ylabel} [{unit}]" if unit else ylabel)
    ax.set_title(title, fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0)
    fig.tight_layout()
    return fig


def _mark_infinite(ax, top: float) -> None:
    """Label the row where infinite errors are drawn (✕ markers)."""
    ax.axhline(top, color="k", lw=0.6, ls=":")
    ax.annotate("✕ = ∞ (false hit/miss)", xy=(0.01, top), xycoords=("axes fraction", "data"), xytext=(0, -12),
                textcoords="offset points", fontsize=7, va="top")


def convergence_column(df: pd.DataFrame) -> str:
    """The error a convergence plot shows: the root finders' iterate error (median over rays,
    finite even when a small budget leaves rays unconverged), else the max error."""
    if "error_iterate_median" in df and pd.to_numeric(df["error_iterate_median"], errors="coerce").notna().any():
        return "error_iterate_median"
    return "error_max"


def convergence_series(df: pd.DataFrame) -> list[dict]:
    """Series of rows (one method × backend of one case × quantity × dtype) in which one integer
    knob varies and every other knob is fixed: the data of a convergence plot."""
    out = []
    ok = _ok(df)
    col = convergence_column(ok)
    for (method, bid), g in ok.groupby(["method", "backend"]):
        knobs = [json.loads(k) for k in g["knobs_json"]]
        if not knobs:
            continue
        names = sorted({n for k in knobs for n, v in k.items() if isinstance(v, int) and not isinstance(v, bool)})
        for name in names:
            groups: dict[str, list[int]] = {}
            for i, k in enumerate(knobs):
                rest = json.dumps({n: v for n, v in k.items() if n != name}, sort_keys=True)
                groups.setdefault(rest, []).append(i)
            for rest, idx in groups.items():
                xs = np.array([knobs[i][name] for i in idx], float)
                if np.unique(xs).size < 3:
                    continue
                order = np.argsort(xs)
                err = pd.to_numeric(g[col], errors="coerce").to_numpy(float)[np.array(idx)][order]
                out.append({"method": method, "backend": bid, "knob": name, "fixed": rest, "x": xs[order],
                            "error": err, "rate": fit_rate(xs[order], err)})
    return out


def plot_convergence(series: list[dict], title: str, q: str, unit: str, col: str = "error_max"):
    fig, ax = plt.subplots(figsize=(7.5, 4.8), dpi=100)
    positive = [e for s in series for e in s["error"] if np.isfinite(e) and e > 0]
    floor = min(positive) / 10 if positive else 1e-16
    top = max(max(positive) * 10 if positive else 1.0, 1.0)
    knob_names = sorted({s["knob"] for s in series})
    for i, s in enumerate(series):
        y = np.where(np.isfinite(s["error"]), np.maximum(s["error"], floor), top)
        rate = f"rate {s['rate']:.2g}" if np.isfinite(s["rate"]) else "no fit"
        label = f"{s['method']} · {s['backend']}" + (f" · {s['knob']}" if len(knob_names) > 1 else "") + f" ({rate})"
        ax.plot(s["x"], y, marker=_MARKERS[i % len(_MARKERS)], lw=1.2, ms=5, label=label)
        bad = ~np.isfinite(s["error"])
        if bad.any():
            ax.scatter(s["x"][bad], y[bad], marker="x", s=60, color="k", zorder=5)
    if any((~np.isfinite(s["error"])).any() for s in series):
        _mark_infinite(ax, top)
    ax.set_xscale("log", base=2)
    what = "median iterate" if col == "error_iterate_median" else "max"
    return _finish(fig, ax, " / ".join(knob_names) + " (knob value, log₂ scale) [count]",
                   f"{what} {q} error over rays", unit, title)


def _save(fig, path: Path) -> bytes:
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, format="png")
    plt.close(fig)
    return path.read_bytes()


def summary_table(df: pd.DataFrame) -> pd.DataFrame:
    """Per case × method × quantity × dtype × backend: the most accurate setting, its time and cost."""
    ok = _ok(df)
    rows = []
    for (cid, method, q, dtype, bid), g in ok.groupby(["case_id", "method", "quantity", "dtype", "backend"]):
        best = g.sort_values(["error_max", "time_median_s"]).iloc[0]
        rows.append({
            "case": cid, "method": method, "quantity": q, "dtype": dtype, "backend": bid,
            "best max error": best["error_max"], "at knob": knob_label(method, best["knob"]),
            "time median [ms]": 1e3 * best["time_median_s"], "time IQR [ms]": 1e3 * best["time_iqr_s"],
            "× closed form": best["time_ratio_cf"], "compile [s]": best["compile_s"],
            "kernel": _kernel(best.get("compile_cache")),
            "evals/ray mean": best["evals_per_ray"], "p99": best.get("evals_p99"), "max": best.get("evals_max"),
            "ray statuses": _statuses(best.get("status_counts")),
        })
    return pd.DataFrame(rows)


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
    for (cid, method, q, dtype, bid), g in ok.groupby(["case_id", "method", "quantity", "dtype", "backend"]):
        row = {"case": cid, "method": method, "quantity": q, "dtype": dtype, "backend": bid}
        for tgt in targets:
            hit = g[g["error_max"] <= tgt].sort_values("time_median_s")
            if hit.empty:
                row[f"≤ {tgt:.0e}"] = "not reached"
                continue
            knob = knob_label(method, hit["knob"].iloc[0])  # "" for a method without knobs: no "@"
            row[f"≤ {tgt:.0e}"] = (f"{1e3 * hit['time_median_s'].iloc[0]:.3g} ms (×{hit['time_ratio_cf'].iloc[0]:.3g})"
                                   + (f" @ {knob}" if knob else ""))
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


def _slug(s: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", s)[:120]


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


def _first_screen_md(fs: dict, md_table) -> list[str]:
    """The first screen (:func:`bench.summary.first_screen`) as Markdown lines."""
    out = []
    if fs["failures"]:
        out += ["## Failed configurations", "", *[f"- {f}" for f in fs["failures"]], ""]
    if fs["regressions"] is not None:
        out += [f"## Regressions against the baseline: {len(fs['regressions'])}", "", md_table(fs["regressions"]), ""]
    out += ["## Which to pick", "", summary.PICK_NOTE, "", md_table(fs["picks"]), ""]
    if fs["scoreboard"]:
        out += ["## Stability scoreboard", "", *[f"- {s}" for s in fs["scoreboard"]], ""]
    if len(fs["claims"]):
        out += ["## Claims of the lecture (failures first)", "", md_table(fs["claims"]), ""]
    return out


def _first_screen_html(fs: dict, table) -> str:
    """The first screen as HTML: failures, regressions, which to pick, stability, claims."""
    e = html.escape
    out = ["<section id='first-screen'>"]
    if fs["failures"]:
        out += ["<h2 class='warn'>Failed configurations</h2><ul>", *[f"<li>{e(f)}</li>" for f in fs["failures"]], "</ul>"]
    if fs["regressions"] is not None:
        out += [f"<h2>Regressions against the baseline: {len(fs['regressions'])}</h2>", table(fs["regressions"])]
    out += ["<h2>Which to pick</h2>", f"<p class='note'>{e(summary.PICK_NOTE)}</p>", table(fs["picks"])]
    if fs["scoreboard"]:
        out += ["<h2>Stability scoreboard</h2><ul>", *[f"<li>{e(s)}</li>" for s in fs["scoreboard"]], "</ul>"]
    if len(fs["claims"]):
        out += ["<h2>Claims of the lecture</h2><p class='note'>One line per claim, failures first; scope, evidence "
                "and plots in the claims ledger at the end.</p>", table(fs["claims"])]
    return "\n".join(out + ["</section>"])


def build(df: pd.DataFrame, env: dict, out_dir: Path, *, scoreboard: list[str] | None = None,
          regressions: pd.DataFrame | None = None) -> None:
    """Write ``report.md``, ``report.html`` and ``plots/*.png`` for results ``df`` into ``out_dir``.

    The first screen (:mod:`bench.summary`) comes first: failures, ``regressions`` against a
    baseline when given, "which to pick", the stability ``scoreboard`` lines and the claims'
    verdicts; then plots; the detail tables last."""
    out_dir = Path(out_dir)
    df = df.copy()
    if "quantity" not in df:
        df["quantity"] = "depth"
    if "family" not in df:
        df["family"] = ""
    df["quantity"] = df["quantity"].fillna("").astype(str)
    df["family"] = df["family"].fillna("").astype(str)
    ok = _ok(df)
    figs: list[tuple[str, str, bytes]] = []  # (section, title, png)
    series_all: list[tuple[str, list[dict]]] = []
    for (fam, cid, q, dtype), g in ok.groupby(["family", "case_id", "quantity", "dtype"]):
        title = f"{fam or 'method'} · {cid} · {q} · {dtype}"
        timed = g[np.isfinite(g["time_median_s"].to_numpy(float)) & (g["time_median_s"].to_numpy(float) > 0)]
        if len(timed):  # accuracy-only runs have no timing
            png = _save(plot_time_vs_error(timed, title), out_dir / "plots" / f"time_{_slug(title)}.png")
            figs.append(("time", title, png))
        series = convergence_series(g)
        if series:
            qn, unit = _label_unit(g)
            png = _save(plot_convergence(series, title, qn, unit, convergence_column(g)), out_dir / "plots" / f"conv_{_slug(title)}.png")
            figs.append(("conv", title, png))
            series_all.append((title, series))
    summ, targets, supp, skipped = summary_table(df), fastest_to_target(df), support_matrix(df), not_run(df)
    compiles = compile_table(df)
    rates = rates_table(series_all)
    stab_cells, stab_note = stability_section(df, out_dir)
    env_df = pd.DataFrame(sorted(env.items()), columns=["key", "value"])
    claims = read_claims(out_dir)
    configs = config_outcomes(df)
    n_ok, n_skip, n_fail = ((configs["outcome"] == o).sum() for o in ("ok", "skipped", "failed"))
    status_line = (f"{n_ok} configurations ran, {n_skip} skipped, {n_fail} failed"
                   + ("" if env.get("complete", "true") == "true" else " — **the run is incomplete** (finish it with --resume)"))
    claims_note = env.get("claims", "")

    def md_img(section):
        return [f"![{t}](plots/{('time_' if s == 'time' else 'conv_') + _slug(t)}.png)" for s, t, _ in figs if s == section]

    def md_table(d: pd.DataFrame) -> str:
        return d.to_markdown(index=False, floatfmt=".3g") if len(d) else "_none_"

    if scoreboard is None and len(stab_cells):
        from . import stability

        scoreboard = stability.scoreboard_lines(stability.scoreboard(stab_cells))
    fs = summary.first_screen(df, env, claims=claims, scoreboard=scoreboard, regressions=regressions)
    md = [f"# isobench report — run {env.get('run_id', '?')}", "",
          f"Suite `{env.get('suite', '?')}`, commit `{env.get('commit', '?')}`, {env.get('cpu', '?')} "
          f"({env.get('cpu_count', '?')} logical CPUs, {env.get('threads', '?')} thread(s) per library). {status_line}.", "",
          *_first_screen_md(fs, md_table),
          "## Best accuracy per backend", "", md_table(summ), "",
          "## Fastest configuration reaching an error target", "", md_table(targets), "",
          *_stability_md(stab_cells, stab_note), "",
          "## Compile time, cold and warm", "", md_table(compiles), "",
          "## Time versus error", "", *md_img("time"), "",
          "## Convergence", "", *md_img("conv"), "", md_table(rates), "",
          "## Support matrix (configurations)", "", md_table(supp), ""]
    if len(skipped):
        md += ["## Skipped or failed, with reasons", "", md_table(skipped), ""]
    if claims is not None or (claims_note and claims_note != "ran"):
        md += ["## Claims ledger", ""]
        if claims_note and claims_note != "ran":
            md += [f"> {claims_note}", ""]
        if claims is not None:
            md += [md_table(claims), ""]
            md += [f"![claim {r.get('id', '')}]({r['plot']})" for _, r in claims.iterrows()
                   if str(r.get("plot", "")) and (out_dir / str(r["plot"])).is_file()]
            md += [""]
    from .sampling import section_md as sampling_md

    sampling_lines = sampling_md(out_dir)
    md += sampling_lines
    spread_lines, spread_workers = spread_section(df, env)
    if spread_lines:
        cells = spread_workers.astype(str).replace(r"\|", r"\\|", regex=True)  # a machine key's '|' is not a column
        md += ["## How the run was spread", "", *[f"- {x}" for x in spread_lines], "", md_table(cells), ""]
    md += ["## Environment", "", md_table(env_df), ""]
    write_text(out_dir / "report.md", "\n".join(md))

    def table(d: pd.DataFrame) -> str:
        if not len(d):
            return "<p class='note'>none</p>"
        return d.to_html(index=False, float_format=lambda v: f"{v:.3g}", border=0, classes="t", na_rep="")

    def img(title: str, png: bytes) -> str:
        return (f"<figure><img alt='{html.escape(title)}' src='data:image/png;base64,{base64.b64encode(png).decode()}'>"
                "</figure>")

    e = html.escape
    style = ("body{font-family:system-ui,sans-serif;max-width:1200px;margin:2em auto;padding:0 1em;color:#222}"
             "table.t{border-collapse:collapse;font-size:13px;margin:0.5em 0}"
             "table.t td,table.t th{border-bottom:1px solid #ddd;padding:3px 8px;text-align:left;vertical-align:top}"
             "table.t th{background:#f3f3f3}h2{border-bottom:2px solid #ccc;padding-bottom:2px}"
             "figure{display:inline-block;margin:0.5em;vertical-align:top}img{max-width:100%}"
             "p.note{color:#555;font-size:14px}.warn{color:#a40}div.scroll{overflow-x:auto}"
             "table.t td{max-width:30em;overflow-wrap:anywhere}"
             "table.stab td,table.stab th{padding:2px 5px;white-space:nowrap}table.stab td{max-width:none}"
             "td.st{font-family:ui-monospace,monospace;font-size:11px}td.ok{background:#e8f5e9}"
             "td.flag{background:#fff8e1}td.bad{background:#fdecea;color:#a00}td.na{color:#999}"
             "ul.board{font-weight:600}")
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>isobench report {e(env.get('run_id', ''))}</title>"
             f"<style>{style}</style></head><body>",
             f"<h1>isobench report</h1><p>Run <code>{e(env.get('run_id', '?'))}</code>, suite "
             f"<code>{e(env.get('suite', '?'))}</code>, commit <code>{e(env.get('commit', '?'))}</code>, "
             f"{e(env.get('cpu', '?'))} ({e(env.get('cpu_count', '?'))} logical CPUs, "
             f"{e(env.get('threads', '?'))} thread(s) per library). {e(status_line).replace('**', '')}.</p>",
             _first_screen_html(fs, table)]
    if len(df):  # a claims-only directory has no results: no empty bench sections
        parts += [
            "<h2>Best accuracy per backend</h2>",
            "<p class='note'>Per case, method and checked quantity: the knob setting with the smallest max error over "
            "all rays. Time is the median over repeated synchronised calls (compile and first call excluded, reported "
            "apart); IQR is its spread. '× closed form' divides by the time of the exact ray–sphere formula on the same "
            "number of rays, measured in the same run — a unit that survives a noisy machine.</p>", table(summ),
            "<h2>Fastest configuration reaching an error target</h2>",
            "<p class='note'>The cheapest knob setting whose max error is at or below the target: median time per "
            "call, its multiple of the closed-form time, and the knob setting.</p>", table(targets),
            _stability_html(stab_cells, stab_note),
            "<h2>Compile time, cold and warm</h2><p class='note'>Per backend: the configurations whose kernel "
            "was compiled in this run (cold) and those that reused one (warm: from the persistent cache, or "
            "compiled earlier in the run for the same structure, its knobs traced).</p>", table(compiles),
            "<h2>Time versus error</h2><p class='note'>One plot per method family, case, quantity and dtype; one "
            "point per knob setting (faint markers), a line through each backend's (and method's) Pareto-optimal "
            "settings; colour = method, marker = backend; lower-left is better. ✕ at the top edge: an infinite error "
            "(a false hit or miss, or a budget that ran out). Grey dashed steps: the Pareto front over every curve.</p>"]
        parts += [img(t, p) for s, t, p in figs if s == "time"]
        parts += ["<h2>Convergence</h2><p class='note'>Error against an integer knob (step budget, iterations, "
                  "samples) with the other knobs fixed, log-log; the legend gives the fitted rate p of error ∝ "
                  "knob<sup>−p</sup> (least squares over the finite, non-zero errors before the error floor; an "
                  "algebraic rate — a geometric convergence shows as a large p).</p>"]
        parts += [img(t, p) for s, t, p in figs if s == "conv"]
        parts += [table(rates)]
        parts += ["<h2>Support matrix</h2><p class='note'>Configurations (case × dtype × knob) per backend and "
                  "method.</p>", table(supp)]
    if len(skipped):
        parts += ["<h2>Skipped or failed, with reasons</h2>", table(skipped)]
    if claims is not None or (claims_note and claims_note != "ran"):
        parts += ["<h2>Claims ledger</h2>"]
        if claims_note and claims_note != "ran":
            parts += [f"<p class='warn'>{e(claims_note)}</p>"]
        if claims is not None:
            parts += [_claims_html(claims, out_dir)]
    if sampling_lines:  # markdown table → HTML through pandas would lose nothing worth the code: shown as text
        parts += ["<h2>Samples to a colour error target</h2>", f"<p class='note'>{e(sampling_lines[2])}</p>",
                  "<pre>" + e(sampling_lines[4]) + "</pre>"]
    if spread_lines:
        parts += ["<h2>How the run was spread</h2><ul>", *[f"<li>{e(x)}</li>" for x in spread_lines], "</ul>",
                  table(spread_workers)]
    parts += ["<h2>Environment</h2>", table(env_df), "</body></html>"]
    write_text(out_dir / "report.html", "\n".join(parts))


STABILITY_DIR = "stability"


def spread_section(df: pd.DataFrame, env: dict) -> tuple[list[str], pd.DataFrame]:
    """Lines and the per-worker table of "How the run was spread" (:mod:`bench.spread`); none for
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
    from . import stability
    from .results import read_results

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


_STABILITY_RULE = (
    "✓ survived: no false hit, no hitting ray reported MISS, every CONVERGED depth within √ε(dtype)·max(1, T) "
    "(T the case's largest depth); ⚑ flagged: no wrong answer, but some rays declined with a failure status "
    "(MAX_ITER, NON_FINITE, LIPSCHITZ_VIOLATED, UNCERTIFIED…) — counts as survived; ✗ failed: a silent wrong "
    "answer or a failed configuration; — not run; ? not judged: the reference flags every ray of the cell's cases "
    "(e.g. exact tangents float64 cannot call a touch or a miss; rays it flags elsewhere are left out). Cells: "
    "mark · max depth error of the CONVERGED rays (— none converged) · worst field evaluations per ray; default "
    "knobs. float32 cells are judged against the float64 rays' exact depths. The Lipschitz methods certify their "
    "answers (docs/methods.md, \"What each root finder can miss\"); the constant-step marchers (march_*) rely on "
    "no bound and may keep ✗ where a feature is crossed twice within their step, their documented limit.")


def _stability_md(cells: pd.DataFrame, note: str) -> list[str]:
    from . import stability

    out = ["## Stability matrix", ""]
    if not len(cells):
        return out + ["_no root finder ran on an adversarial case (the quick suite's stability stage or "
                      "`python -m bench run --suite stability` runs them)_"]
    out += [f"- {line}" for line in stability.scoreboard_lines(stability.scoreboard(cells))]
    out += ["", f"{_STABILITY_RULE} Source: {note}.", "",
            stability.stability_matrix(cells).to_markdown(index=False), ""]
    bad = cells[cells["verdict"].isin(["failed", "flagged"])]
    if len(bad):
        out += ["Failed and flagged cells:", ""]
        out += [f"- {r['method']} · {r['backend']} · {r['dtype']} · {r['family']}: {stability.cell_detail(r)}"
                for _, r in bad.iterrows()]
    return out


def _stability_html(cells: pd.DataFrame, note: str) -> str:
    from . import stability

    e = html.escape
    head = "<h2 id='stability'>Stability matrix</h2>"
    if not len(cells):
        return head + ("<p class='note'>No root finder ran on an adversarial case (the quick suite's stability "
                       "stage or <code>python -m bench run --suite stability</code> runs them).</p>")
    board = "".join(f"<li>{e(line)}</li>" for line in stability.scoreboard_lines(stability.scoreboard(cells)))
    m = stability.stability_matrix(cells, detail=True)
    fams = [c for c in m.columns if c not in ("method", "backend", "dtype")]
    cls = {"✓": "ok", "⚑": "flag", "✗": "bad", "—": "na"}
    rows = []
    for _, r in m.iterrows():
        tds = "".join(f"<td>{e(str(r[c]))}</td>" for c in ("method", "backend", "dtype"))
        for f in fams:
            text, detail = r[f]
            tds += f"<td class='st {cls.get(text[:1], 'na')}' title='{e(detail)}'>{e(text)}</td>"
        rows.append(f"<tr>{tds}</tr>")
    th = "".join(f"<th>{e(c)}</th>" for c in ["method", "backend", "dtype"] + fams)
    return (head + f"<ul class='board'>{board}</ul><p class='note'>{e(_STABILITY_RULE)} Hover a cell for its "
            f"statuses, false hits and misses, and cases. Source: {e(note)}.</p>"
            f"<div class='scroll'><table class='t stab'><tr>{th}</tr>{''.join(rows)}</table></div>")


def _claims_html(claims: pd.DataFrame, run_dir: Path) -> str:
    """The ledger as a table, one row per claim, with its plot inlined below the row."""
    cols = [c for c in CLAIM_COLUMNS if c in claims.columns and c != "plot"]
    cols += [c for c in claims.columns if c not in CLAIM_COLUMNS]
    head = "".join(f"<th>{html.escape(c)}</th>" for c in cols)

    def is_warn(verdict: str) -> bool:
        return verdict.lower() not in ("holds", "true", "confirmed")

    def cell(c: str, v, verdict: str) -> str:
        text = html.escape(str(v))
        if c == "key_numbers" and len(text) > 200:  # long evidence folds away; the verdict stays in view
            text = f"<details><summary>{text[:120]}…</summary>{text}</details>"
        return f"<td{' class=warn' if c == 'verdict' and is_warn(verdict) else ''}>{text}</td>"

    # A one-line-per-claim summary first (failures first), so a reader sees every verdict, and the scope
    # it was judged in, before the evidence.
    short = [c for c in ("id", "statement", "scope", "verdict", "conditions", "counterexample") if c in claims.columns]
    summary = "".join(
        "<tr>" + "".join(cell(c, r[c], str(r.get("verdict", ""))) for c in short) + "</tr>"
        for _, r in claims_in_reading_order(claims).iterrows())
    names = {"conditions": "holds on (named class)", "counterexample": "counterexample (inside the scope)"}
    summary_html = (f"<table class='t'><tr>{''.join(f'<th>{names.get(c, c)}</th>' for c in short)}</tr>{summary}</table>"
                    "<h3>Evidence, claim by claim</h3>")
    body = []
    for _, r in claims.iterrows():
        verdict = str(r.get("verdict", ""))
        body.append("<tr>" + "".join(cell(c, r[c], verdict) for c in cols) + "</tr>")
        plot = str(r.get("plot", "") or "")
        p = Path(run_dir) / plot
        if plot and p.is_file() and p.suffix.lower() == ".png":
            b64 = base64.b64encode(p.read_bytes()).decode()
            body.append(f"<tr><td colspan='{len(cols)}' style='max-width:none'><img style='max-width:1000px' alt='claim {html.escape(str(r.get('id', '')))}' "
                        f"src='data:image/png;base64,{b64}'></td></tr>")
        elif plot:
            body.append(f"<tr><td colspan='{len(cols)}' class='warn'>plot {html.escape(plot)} not found</td></tr>")
    return summary_html + f"<div class='scroll'><table class='t'><tr>{head}</tr>{''.join(body)}</table></div>"


def build_from_dir(run_dir: Path) -> None:
    from .results import read_results

    run_dir = Path(run_dir)
    env = json.loads((run_dir / "environment.json").read_text())
    try:
        df = read_results(run_dir)
    except FileNotFoundError:  # a claims-only directory
        from .results import COLUMNS

        df = pd.DataFrame(columns=COLUMNS + ["knobs_json"])
    build(df, env, run_dir)
