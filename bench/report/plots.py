"""The report's plots: time versus error (one curve per method and backend, the Pareto front
over all of them) and convergence (error against an integer knob, with its fitted rate), as PNG
files under ``plots/`` (:func:`figure_jobs`, drawn by :func:`start_rendering`)."""

from __future__ import annotations

import concurrent.futures
import itertools
import json
import multiprocessing
import re
from pathlib import Path
from typing import Callable

import matplotlib

matplotlib.use("Agg")  # files only, never a window
import matplotlib.pyplot as plt  # noqa: E402
import matplotlib.ticker  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from . import summary  # noqa: E402

_MARKERS = "osD^v<>ph*"


_LINESTYLES = ["-", "--", ":", "-."]


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


#: superscript forms of what a log axis's exponents contain
_SUPERSCRIPT = str.maketrans("0123456789-−+", "⁰¹²³⁴⁵⁶⁷⁸⁹⁻⁻⁺")


def plain_tick_label(label: str) -> str:
    """A log-axis tick label of matplotlib's (``$\\mathdefault{2\\times10^{-3}}$``) in plain
    Unicode ("2×10⁻³"); a label it cannot rewrite exactly (a fractional exponent) is returned as
    it is."""
    m = re.fullmatch(r"\$\\mathdefault\{(.*)\}\$", label)
    if not m:
        return label
    body = m.group(1).replace("\\times", "×")
    out = re.sub(r"\^\{([-−+]?[0-9]+)\}", lambda e: e.group(1).translate(_SUPERSCRIPT), body)
    return label if any(c in out for c in "\\^{}$") else out


class PlainLogFormatter(matplotlib.ticker.LogFormatterSciNotation):
    """matplotlib's log-axis labels (which ticks get one is its choice, unchanged), written in
    Unicode superscripts instead of mathtext (:func:`plain_tick_label`).  Why not matplotlib's
    own: mathtext parses every distinct label with pyparsing, ~27 ms a label here, and a quick
    run's 31 figures spent 9 of their 58 s (one process, profiled) parsing ~330 labels."""

    def __call__(self, x, pos=None):
        return plain_tick_label(super().__call__(x, pos))


def _plain_log_labels(ax) -> None:
    """:class:`PlainLogFormatter` on the log axes of ``ax``, with the settings matplotlib gave them."""
    for axis in (ax.xaxis, ax.yaxis):
        for get, put in ((axis.get_major_formatter, axis.set_major_formatter),
                         (axis.get_minor_formatter, axis.set_minor_formatter)):
            f = get()
            if type(f) is matplotlib.ticker.LogFormatterSciNotation:
                put(PlainLogFormatter(axis.get_transform().base, labelOnlyBase=f.labelOnlyBase,
                                      minor_thresholds=f.minor_thresholds))


def _finish(fig, ax, xlabel: str, ylabel: str, unit: str, title: str):
    """Log y axis, labels with units, grid, the legend outside the axes (never over the data)."""
    ax.set_yscale("log")
    _plain_log_labels(ax)
    # minor labels (2×10ⁿ, 3×10ⁿ, … on an axis spanning about a decade) at a smaller size: at the
    # major labels' size neighbours such as 3×10⁻² and 4×10⁻² ran into each other
    ax.tick_params(which="minor", labelsize=7)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(f"{ylabel} [{unit}]" if unit else ylabel)
    ax.set_title(title, fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0)
    fig.tight_layout()
    # tight_layout leaves a placeholder layout engine behind, and savefig then draws the whole
    # figure once more before drawing it (matplotlib 3.11, backend_bases.print_figure): without
    # the engine, the same PNG bytes (31 of 31 figures of a quick run) in 8 % less time
    fig.set_layout_engine(None)
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
    """One curve per series (:func:`convergence_series`), labelled with its fitted rate; the figure
    grows with the legend (one entry per series, beside the axes), so that many series (the
    quick run's 36 volume renderers × backends on one case) never squeeze the axes."""
    fig, ax = plt.subplots(figsize=(7.5, max(4.8, 0.17 * (len(series) + 1) + 1.0)), dpi=100)
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


def _slug(s: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", s)[:120]



def _render(job: tuple) -> bytes:
    """One figure of :func:`figure_jobs` drawn and written: ``("time", title, rows, path)`` or
    ``("conv", title, (series, quantity, unit, column), path)``; returns the PNG's bytes."""
    kind, title, data, path = job
    fig = plot_time_vs_error(data, title) if kind == "time" else plot_convergence(data[0], title, *data[1:])
    return _save(fig, path)


#: figures from which :func:`start_rendering` draws in worker processes (below it, a pool's start costs
#: more than it saves: about 1 s to import matplotlib and pandas in each worker, 0.3–0.7 s a figure)
POOL_FROM = 12


def start_rendering(jobs: list[tuple]) -> Callable[[], list[bytes]]:
    """Start :func:`_render` of every job and return ``collect()``, which waits for them and gives
    their PNGs in job order.  Where there are ≥ 2 cores and ≥ :data:`POOL_FROM` jobs, worker
    processes (one fewer than the usable cores, at most 3; ``spawn``: no forked copy of the
    caller's thread pools) draw the jobs from the first on, so that the caller can build the
    report's tables meanwhile; ``collect()`` then draws, from the last job backwards, every job
    no worker has started (a pending future it can cancel), so the caller's core draws too once
    its tables are done, until the two meet.  Without a pool, or for the jobs a pool that could
    not start or broke left undone, ``collect()`` draws them here.  Why: the figures are
    independent, and a quick run's ~30 of them took 20 s of its report's 25 s on one core
    (tight layout and tick-label text extents are most of it); two workers on two cores left the
    caller idle for the last ~2 s of a quick run's report, one worker and the caller does not."""
    from ..run.environment import usable_cores

    cores = usable_cores()
    ex, futures = None, []
    if cores >= 2 and len(jobs) >= POOL_FROM:
        try:
            ex = concurrent.futures.ProcessPoolExecutor(max_workers=min(cores - 1, 3),
                                                        mp_context=multiprocessing.get_context("spawn"))
            futures = [ex.submit(_render, job) for job in jobs]
        except (OSError, concurrent.futures.process.BrokenProcessPool):
            futures = []  # drawn by collect() instead: the report is never lost to a pool that could not run

    def collect() -> list[bytes]:
        out: list = [None] * len(jobs)
        try:
            pending = list(itertools.zip_longest(range(len(jobs)), futures))
            for i, fut in reversed(pending):  # the caller takes the jobs no worker has started
                if fut is None or fut.cancel():
                    out[i] = _render(jobs[i])
            for i, fut in pending:
                if out[i] is None:
                    try:
                        out[i] = fut.result()
                    except (OSError, concurrent.futures.process.BrokenProcessPool):
                        out[i] = _render(jobs[i])
        finally:
            if ex is not None:
                ex.shutdown(cancel_futures=True)
        return out

    return collect


def figure_jobs(df: pd.DataFrame, out_dir: Path) -> tuple[list[tuple], list[tuple[str, list[dict]]]]:
    """The plots of a run's measured rows, one per method family × case × quantity × dtype, as
    jobs for :func:`start_rendering` (each written to ``out_dir/plots``): ([(kind "time"/"conv",
    title, data, path)], [(title, convergence series)])."""
    jobs, series_all = [], []
    for (fam, cid, q, dtype), g in _ok(df).groupby(["family", "case_id", "quantity", "dtype"]):
        title = f"{fam or 'method'} · {cid} · {q} · {dtype}"
        timed = g[np.isfinite(g["time_median_s"].to_numpy(float)) & (g["time_median_s"].to_numpy(float) > 0)]
        if len(timed):  # accuracy-only runs have no timing
            jobs.append(("time", title, timed, out_dir / f"plots/time_{_slug(title)}.png"))
        series = convergence_series(g)
        if series:
            qn, unit = _label_unit(g)
            jobs.append(("conv", title, (series, qn, unit, convergence_column(g)),
                         out_dir / f"plots/conv_{_slug(title)}.png"))
            series_all.append((title, series))
    return jobs, series_all
