"""How a run was spread over processes, and a projection of its wall time on more of them.

Reads only a results set and its ``environment.json`` (no dask needed): each row records the
process that measured it (``worker``, ``worker_pid``, ``machine_key``; an empty ``worker`` is a
single-process run's own process) and ``task_s``, its configuration's wall seconds there.  A
cluster run (:mod:`bench.run.cluster`) also records in environment.json the seconds of its reference
tasks (``cluster.reference_task_s``), the longest dependency chain (``cluster.critical_path_s``),
the measured per-task overhead (``cluster.overhead_s``: a task's latency seen by the client
minus its time on the worker) and the central cost per task (``cluster.central_s``: scheduler and
client, from a burst of empty tasks at start-up).

Projection (:func:`project`), for P workers, of the configurations stage's wall time:

    T(P) = max( LS_P(t_i + o),  N · c,  C )

* LS_P: greedy list scheduling of the measured task times t_i (configurations in plan order,
  reference tasks first), each task handed to the worker that frees first — what the client's
  flow control does; o, the mean per-task overhead, keeps a worker idle between two tasks;
* N · c: the central bound — the scheduler and the client handle N tasks one after the other;
* C: the critical path — the longest task, or the longest chain of reference tasks (a case's
  rendering integrals, one after the other) plus the longest configuration that waits for it.

Assumptions, stated with every projection: the P workers are as fast as those measured (task
times carry over), each worker has its cores to itself, start-up (imports, cluster start) is
not included, and compile-on-first-call costs stay per configuration (each configuration is
prepared afresh, so a new worker pays nothing a measured one did not).
"""

from __future__ import annotations

import heapq
import json
from pathlib import Path

import numpy as np
import pandas as pd

CONFIG_KEY = ["case_id", "backend", "dtype", "method", "knob"]
#: worker counts a projection shows by default
WORKERS = (1, 2, 4, 8, 16, 32, 64)


def _num(v, default=float("nan")) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return default
    return f


def _json(env: dict, key: str, default):
    try:
        return json.loads(env.get(key) or "null") or default
    except ValueError:
        return default


def configurations(df: pd.DataFrame) -> pd.DataFrame:
    """One row per configuration (its quantity rows share process and ``task_s``), with
    ``worker`` ("" → "this process"), ``worker_pid``, ``machine_key`` and ``task_s`` filled."""
    if not len(df):
        return pd.DataFrame(columns=CONFIG_KEY + ["worker", "worker_pid", "machine_key", "task_s"])
    d = df.drop_duplicates(CONFIG_KEY).copy()
    for c in ("worker", "machine_key"):
        d[c] = d[c].fillna("").astype(str) if c in d else ""
    d["worker"] = d["worker"].replace("", "this process")
    d["worker_pid"] = pd.to_numeric(d["worker_pid"], errors="coerce") if "worker_pid" in d else np.nan
    d["task_s"] = pd.to_numeric(d["task_s"], errors="coerce") if "task_s" in d else np.nan
    return d


def per_worker(df: pd.DataFrame) -> pd.DataFrame:
    """Per process (a dask worker's address and pid, or "this process"): machine key,
    configurations, their task seconds (sum, median, max)."""
    d = configurations(df)
    if not len(d):
        return pd.DataFrame(columns=["worker", "pid", "machine key", "configurations", "task s (sum)",
                                     "task s (median)", "task s (max)"])
    d["pid"] = d["worker_pid"].map(lambda v: "" if pd.isna(v) else str(int(v)))
    g = d.groupby(["worker", "pid", "machine_key"], sort=True, dropna=False)
    out = g["task_s"].agg(["count", "sum", "median", "max"]).reset_index()
    out.columns = ["worker", "pid", "machine key", "configurations", "task s (sum)", "task s (median)",
                   "task s (max)"]
    return out


def summary(df: pd.DataFrame, env: dict) -> dict:
    """What a reader needs to judge how the run was spread (values as numbers or strings)."""
    d = configurations(df)
    cluster = env.get("cluster", "")
    wall = _num(env.get("cluster.execute_s"), _num(env.get("elapsed_s")))
    task_sum = float(np.nansum(d["task_s"])) if len(d) else 0.0
    ref = [float(x) for x in _json(env, "cluster.reference_task_s", [])]
    processes = d["worker"].nunique() if len(d) else 0
    workers = int(_num(env.get("cluster.workers_max"), processes or 1))
    busy = task_sum + sum(ref)
    overhead = _json(env, "cluster.overhead_s", {})
    return {
        "cluster": cluster or "none (one process)",
        "workers at once": workers,
        "processes that ran configurations": processes,
        "machine keys": sorted(k for k in d["machine_key"].unique() if k) if len(d) else [],
        "configurations": len(d),
        "configurations without task time": int(d["task_s"].isna().sum()) if len(d) else 0,
        "wall s": wall,
        "task s (sum)": task_sum,
        "reference tasks": len(ref),
        "reference task s (sum)": float(sum(ref)),
        "parallel efficiency": busy / (wall * workers) if wall and wall > 0 and workers else float("nan"),
        "overhead s per task (mean)": _num(overhead.get("mean")),
        "overhead s per task (median)": _num(overhead.get("median")),
        "central s per task": _num(env.get("cluster.central_s")),
        "critical path s": _num(env.get("cluster.critical_path_s")),
        "workers died": int(_num(env.get("cluster.workers_died"), 0)),
        "killed-worker failures": int(d["reason"].fillna("").astype(str).str.startswith("KilledWorker").sum())
        if "reason" in d and len(d) else 0,
    }


def list_schedule(durations: np.ndarray, workers: int) -> float:
    """Makespan of greedy list scheduling: tasks in the given order, each to the worker that
    frees first (a min-heap of the workers' free times)."""
    if workers < 1:
        raise ValueError(f"workers must be ≥ 1, got {workers}")
    free = [0.0] * min(workers, max(len(durations), 1))
    for t in durations:
        heapq.heappush(free, heapq.heappop(free) + float(t))
    return max(free)


def project(df: pd.DataFrame, env: dict, workers=WORKERS, overhead_s: float | None = None,
            central_s: float | None = None) -> tuple[pd.DataFrame, list[str]]:
    """Projected wall time of the configurations stage on each worker count (module docstring's
    model), and notes (the parameters used, where they come from, what is assumed).
    ``overhead_s``/``central_s``: override the run's measured values (a single-process run has
    none: without them the projection is a lower bound, and says so)."""
    d = configurations(df)
    t = d["task_s"].to_numpy(float) if len(d) else np.zeros(0)
    missing = int(np.isnan(t).sum())
    t = t[~np.isnan(t)]
    ref = np.array([float(x) for x in _json(env, "cluster.reference_task_s", [])])
    notes = []
    o_meas = _num(_json(env, "cluster.overhead_s", {}).get("mean"))
    c_meas = _num(env.get("cluster.central_s"))
    o = overhead_s if overhead_s is not None else (o_meas if np.isfinite(o_meas) else 0.0)
    c = central_s if central_s is not None else (c_meas if np.isfinite(c_meas) else 0.0)
    src_o = "given" if overhead_s is not None else ("measured in this run" if np.isfinite(o_meas) else "unknown: 0")
    src_c = "given" if central_s is not None else ("measured in this run" if np.isfinite(c_meas) else "unknown: 0")
    notes.append(f"per-task overhead o = {o * 1e3:.1f} ms ({src_o}); central cost c = {c * 1e3:.2f} ms per task "
                 f"({src_c})")
    if "unknown" in src_o or "unknown" in src_c:
        notes.append("a run without cluster measurements: the projection is a lower bound (pass --overhead-s and "
                     "--central-s, e.g. from a --cluster run on the same machine)")
    if missing:
        notes.append(f"{missing} configurations have no task_s (rows written before it was recorded): left out")
    crit = max(_num(env.get("cluster.critical_path_s"), 0.0), float(t.max()) if t.size else 0.0)
    durations = np.concatenate([ref, t]) + o
    n = durations.size
    rows = []
    for p in workers:
        ls = list_schedule(durations, p) if n else 0.0
        central = n * c
        wall = max(ls, central, crit)
        # the list schedule cannot end before its longest task: within 1 % of the critical path
        # it is that task (or chain), not the number of workers, that sets the wall time
        bound = ("central (scheduler and client)" if wall == central and central > ls else
                 "critical path" if crit >= 0.99 * wall else "workers")
        rows.append({"workers": p, "projected wall s": wall, "list schedule s": ls, "central bound s": central,
                     "critical path s": crit, "speed-up vs 1": float("nan"), "limited by": bound})
    out = pd.DataFrame(rows)
    if len(out):
        one = list_schedule(durations, 1) if n else 0.0
        out["speed-up vs 1"] = one / out["projected wall s"].where(out["projected wall s"] > 0)
    notes.append(f"{len(t)} configuration tasks ({float(t.sum()):.1f} s) and {ref.size} reference tasks "
                 f"({float(ref.sum()):.1f} s); longest chain {crit:.1f} s. Assumes workers as fast as those measured, "
                 "each with its cores to itself; start-up (imports, cluster start) not included")
    return out, notes


def model_check(df: pd.DataFrame, env: dict) -> str:
    """The model applied to the run's own worker count, against the wall time it measured."""
    s = summary(df, env)
    p = max(int(s["workers at once"]), 1)
    proj, _ = project(df, env, workers=(p,))
    if not len(proj) or not np.isfinite(s["wall s"]):
        return ""
    got = float(proj["projected wall s"].iloc[0])
    return (f"model check: {p} worker(s) projected {got:.1f} s, measured {s['wall s']:.1f} s "
            f"({got / s['wall s'] - 1:+.0%})" if s["wall s"] > 0 else "")


def text(run_dir: Path, workers=WORKERS, overhead_s: float | None = None, central_s: float | None = None) -> str:
    """``python -m bench spread RUN_DIR``: the spread summary, the per-worker table and the projection."""
    from ..run.results import read_results

    run_dir = Path(run_dir)
    env = json.loads((run_dir / "environment.json").read_text())
    df = read_results(run_dir)
    s = summary(df, env)
    lines = [f"Run {env.get('run_id', '?')}: how it was spread"]
    lines += [f"  {k}: {v:.3g}" if isinstance(v, float) else f"  {k}: {v}" for k, v in s.items()]
    lines += ["", per_worker(df).to_string(index=False, float_format=lambda v: f"{v:.3g}"), ""]
    proj, notes = project(df, env, workers, overhead_s, central_s)
    lines += ["Projection of the configurations stage (T(P) = max(list schedule of t_i + o, N·c, critical path)):",
              proj.to_string(index=False, float_format=lambda v: f"{v:.4g}")]
    lines += [f"  {n}" for n in notes]
    check = model_check(df, env) if overhead_s is None and central_s is None else ""
    if check:
        lines.append(f"  {check}")
    return "\n".join(lines)
