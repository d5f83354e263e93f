"""Reports: ``report.md`` and a self-contained ``report.html`` (plots inlined as PNG).

Reading the time-versus-error plot: one curve per backend, one point per knob setting; x is
the median wall time of one call over all rays of the case (log scale, seconds), y the largest
depth error over all rays (log scale, scene units).  Points at the top edge marked ✕ have an
infinite error: some ray got a false hit or a false miss (budget exhausted).  Lower-left is
better; the Pareto front over all backends is the dashed line.
"""

from __future__ import annotations

import base64
import html
import io
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from .results import write_text  # noqa: E402

_MARKERS = "osD^v<>ph*"


def pareto_front(times: np.ndarray, errors: np.ndarray) -> np.ndarray:
    """Indices of the points not dominated in (time, error), sorted by time."""
    order = np.lexsort((errors, times))
    front, best = [], np.inf
    for i in order:
        if errors[i] < best:
            front.append(i)
            best = errors[i]
    return np.array(front, dtype=int)


def plot_time_vs_error(df: pd.DataFrame, title: str):
    fig, ax = plt.subplots(figsize=(7.5, 4.8), dpi=110)
    ok = df[df["outcome"] == "ok"].copy()
    finite = ok["error_max"].replace([np.inf], np.nan).dropna()
    positive = finite[finite > 0]
    floor = positive.min() / 10 if len(positive) else 1e-16
    top = max(positive.max() * 10 if len(positive) else 1.0, 1.0)
    for k, (bid, g) in enumerate(sorted(ok.groupby("backend"), key=lambda kv: kv[0])):
        g = g.sort_values("time_median_s")
        err = g["error_max"].to_numpy(float)
        y = np.where(np.isfinite(err), np.maximum(err, floor), top)
        t = g["time_median_s"].to_numpy(float)
        ax.plot(t, y, marker=_MARKERS[k % len(_MARKERS)], lw=1.2, ms=5, label=bid)
        bad = ~np.isfinite(err)
        if bad.any():
            ax.scatter(t[bad], y[bad], marker="x", s=60, color="k", zorder=5)
    if len(ok):
        err = ok["error_max"].to_numpy(float)
        fin = np.isfinite(err)
        if fin.any():
            t = ok["time_median_s"].to_numpy(float)[fin]
            e = np.maximum(err[fin], floor)
            f = pareto_front(t, e)
            ax.plot(t[f], e[f], ls="--", color="0.4", lw=1, label="Pareto front", drawstyle="steps-post")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("median time per call over all rays [s]")
    ax.set_ylabel("max depth error over rays [scene units]")
    ax.set_title(title, fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    fig.tight_layout()
    return fig


def _png_b64(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode()


def summary_table(df: pd.DataFrame) -> pd.DataFrame:
    """Per case × method × dtype × backend: median time of the most accurate setting and more."""
    ok = df[df["outcome"] == "ok"]
    rows = []
    for (cid, method, dtype, bid), g in ok.groupby(["case_id", "method", "dtype", "backend"]):
        best = g.sort_values(["error_max", "time_median_s"]).iloc[0]
        rows.append({
            "case": cid, "method": method, "dtype": dtype, "backend": bid,
            "best error_max": best["error_max"], "at knob": best["knob"],
            "time median [ms]": 1e3 * best["time_median_s"], "time IQR [ms]": 1e3 * best["time_iqr_s"],
            "× closed form": best["time_ratio_cf"], "compile [s]": best["compile_s"],
            "evals/ray": best["evals_per_ray"],
        })
    return pd.DataFrame(rows)


def support_matrix(df: pd.DataFrame) -> pd.DataFrame:
    """backend × method: how many configurations ran, were skipped or failed."""
    t = df.groupby(["backend", "method", "outcome"]).size().unstack(fill_value=0)
    for c in ("ok", "skipped", "failed"):
        if c not in t.columns:
            t[c] = 0
    return t[["ok", "skipped", "failed"]].reset_index()


def not_run(df: pd.DataFrame) -> pd.DataFrame:
    bad = df[df["outcome"] != "ok"]
    return bad.groupby(["outcome", "backend", "method", "reason"]).size().rename("configurations").reset_index()


def build(df: pd.DataFrame, env: dict, out_dir: Path) -> None:
    out_dir = Path(out_dir)
    plots: list[tuple[str, str]] = []
    for (cid, method, dtype), g in df.groupby(["case_id", "method", "dtype"]):
        if (g["outcome"] == "ok").any():
            title = f"{cid} · {method} · {dtype}"
            plots.append((title, _png_b64(plot_time_vs_error(g, title))))
    summ, supp, skipped = summary_table(df), support_matrix(df), not_run(df)
    env_df = pd.DataFrame(sorted(env.items()), columns=["key", "value"])

    md = [f"# isobench report — run {env.get('run_id', '?')}", "",
          f"Suite `{env.get('suite', '?')}`, commit `{env.get('commit', '?')}`, {env.get('cpu', '?')} "
          f"({env.get('cpu_count', '?')} logical CPUs).", "",
          "## Fastest setting at best accuracy, per backend", "", summ.to_markdown(index=False, floatfmt=".3g"), "",
          "## Support matrix (configurations)", "", supp.to_markdown(index=False), ""]
    if len(skipped):
        md += ["## Skipped or failed, with reasons", "", skipped.to_markdown(index=False), ""]
    md += ["## Time versus error", "", "See report.html for the plots (one per case × method × dtype).", "",
           "## Environment", "", env_df.to_markdown(index=False), ""]
    write_text(out_dir / "report.md", "\n".join(md))

    def table(d: pd.DataFrame) -> str:
        return d.to_html(index=False, float_format=lambda v: f"{v:.3g}", border=0, classes="t", na_rep="")

    style = ("body{font-family:system-ui,sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;color:#222}"
             "table.t{border-collapse:collapse;font-size:13px;margin:0.5em 0}"
             "table.t td,table.t th{border-bottom:1px solid #ddd;padding:3px 8px;text-align:right}"
             "table.t th{background:#f3f3f3}h2{border-bottom:2px solid #ccc;padding-bottom:2px}"
             "figure{display:inline-block;margin:0.5em}img{max-width:100%}p.note{color:#555;font-size:14px}")
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>isobench report {html.escape(env.get('run_id', ''))}</title>"
             f"<style>{style}</style></head><body>",
             f"<h1>isobench report</h1><p>Run <code>{html.escape(env.get('run_id', '?'))}</code>, suite "
             f"<code>{html.escape(env.get('suite', '?'))}</code>, commit <code>{html.escape(env.get('commit', '?'))}</code>, "
             f"{html.escape(env.get('cpu', '?'))} ({html.escape(env.get('cpu_count', '?'))} logical CPUs).</p>",
             "<h2>Fastest setting at best accuracy, per backend</h2>",
             "<p class='note'>Time is the median over repeated synchronised calls (compile and first call excluded, "
             "reported apart); IQR is its spread. '× closed form' divides by the time of the exact ray–sphere formula "
             "on the same number of rays, measured in the same run.</p>", table(summ),
             "<h2>Time versus error</h2><p class='note'>One point per knob setting; lower-left is better. "
             "✕ at the top edge: infinite error (a false hit or miss). Dashed: Pareto front over all backends.</p>"]
    parts += [f"<figure><img alt='{html.escape(t)}' src='data:image/png;base64,{b}'></figure>" for t, b in plots]
    parts += ["<h2>Support matrix</h2>", table(supp)]
    if len(skipped):
        parts += ["<h2>Skipped or failed, with reasons</h2>", table(skipped)]
    parts += ["<h2>Environment</h2>", table(env_df), "</body></html>"]
    write_text(out_dir / "report.html", "\n".join(parts))


def build_from_dir(run_dir: Path) -> None:
    from .results import read_results

    run_dir = Path(run_dir)
    env = json.loads((run_dir / "environment.json").read_text())
    build(read_results(run_dir), env, run_dir)
