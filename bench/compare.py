"""Compare two result sets: accuracy by tolerance, timing by factor *and* significance.

Rows are matched on (case_id, backend, dtype, method, knob).  Verdicts per row:

* ``not comparable``: the case versions differ (the case changed), or for timing the machines
  differ; a row present on one side only is ``missing``/``new``.
* accuracy ``worse`` when the new max depth error exceeds ``base·(1 + rtol) + atol[dtype]``
  (atol = ``atol_eps`` × the dtype's eps), when false hits/misses increase, or when a row that
  ran now fails.  Accuracy is deterministic, so no statistics are needed.
* timing ``worse``/``better`` only when the median ratio is beyond ``factor`` (default 1.1) *and*
  the samples differ significantly: a one-sided Mann–Whitney U test at ``alpha`` (asv's and
  pyperf's practice) when both sides have ≥ 5 samples, else non-overlapping sample ranges.
  Otherwise ``not significant``.

The exit status of ``python -m bench compare`` is 1 when any row is ``worse`` (timing rows
only when ``--timing`` is given; CI compares accuracy against a baseline from another machine).
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
from scipy.stats import mannwhitneyu

from .results import KEY

ATOL_EPS = 1000.0


def _samples(v) -> np.ndarray:
    if isinstance(v, str) and v:
        return np.asarray(json.loads(v), float)
    return np.zeros(0)


def timing_verdict(base_samples: np.ndarray, new_samples: np.ndarray, factor: float = 1.1, alpha: float = 0.01) -> tuple[str, float, float]:
    """(verdict, median ratio new/base, p-value or NaN)."""
    if base_samples.size == 0 or new_samples.size == 0:
        return "not comparable", float("nan"), float("nan")
    ratio = float(np.median(new_samples) / np.median(base_samples))
    if base_samples.size >= 5 and new_samples.size >= 5:
        p_slower = mannwhitneyu(new_samples, base_samples, alternative="greater").pvalue
        p_faster = mannwhitneyu(new_samples, base_samples, alternative="less").pvalue
        if ratio > factor and p_slower < alpha:
            return "worse", ratio, float(p_slower)
        if ratio < 1 / factor and p_faster < alpha:
            return "better", ratio, float(p_faster)
        return "not significant", ratio, float(min(p_slower, p_faster))
    if ratio > factor and new_samples.min() > base_samples.max():
        return "worse", ratio, float("nan")
    if ratio < 1 / factor and new_samples.max() < base_samples.min():
        return "better", ratio, float("nan")
    return "not significant", ratio, float("nan")


def accuracy_verdict(b: pd.Series, n: pd.Series, rtol: float = 0.1, atol_eps: float = ATOL_EPS) -> str:
    if b["outcome"] != "ok":
        return "not comparable" if n["outcome"] != "ok" else "better"
    if n["outcome"] != "ok":
        return "worse"
    eb, en = float(b["error_max"]), float(n["error_max"])
    atol = atol_eps * float(np.finfo(str(n["dtype"])).eps)
    worse_misses = (int(n["n_false_hit"]) > int(b["n_false_hit"])) or (int(n["n_false_miss"]) > int(b["n_false_miss"]))
    if worse_misses or (np.isfinite(eb) and not np.isfinite(en)) or (np.isfinite(en) and en > eb * (1 + rtol) + atol):
        return "worse"
    if (np.isfinite(en) and not np.isfinite(eb)) or (np.isfinite(eb) and eb > en * (1 + rtol) + atol):
        return "better"
    return "same"


def compare(base: pd.DataFrame, new: pd.DataFrame, *, factor: float = 1.1, alpha: float = 0.01, rtol: float = 0.1,
            atol_eps: float = ATOL_EPS, same_machine: bool = True) -> pd.DataFrame:
    m = base.merge(new, on=KEY, how="outer", suffixes=("_base", "_new"), indicator=True)
    rows = []
    for _, r in m.iterrows():
        key = {k: r[k] for k in KEY}
        if r["_merge"] == "left_only":
            rows.append({**key, "accuracy": "missing", "timing": "missing"})
            continue
        if r["_merge"] == "right_only":
            rows.append({**key, "accuracy": "new", "timing": "new"})
            continue
        b = pd.Series({c[:-5]: r[c] for c in m.columns if c.endswith("_base")} | key)
        n = pd.Series({c[:-4]: r[c] for c in m.columns if c.endswith("_new")} | key)
        if b["case_version"] != n["case_version"]:
            rows.append({**key, "accuracy": "not comparable", "timing": "not comparable",
                         "note": f"case version {b['case_version']} → {n['case_version']}"})
            continue
        acc = accuracy_verdict(b, n, rtol, atol_eps)
        if same_machine and b["outcome"] == "ok" and n["outcome"] == "ok":
            tv, ratio, p = timing_verdict(_samples(b["time_samples_s"]), _samples(n["time_samples_s"]), factor, alpha)
        else:
            tv, ratio, p = "not comparable", float("nan"), float("nan")
        rows.append({**key, "accuracy": acc, "error_base": b.get("error_max"), "error_new": n.get("error_max"),
                     "timing": tv, "time_ratio": ratio, "p_value": p})
    return pd.DataFrame(rows)
