"""Compare two result sets: accuracy by tolerance per dtype, timing by factor *and* significance.

Rows are matched on ``results.KEY`` (case, backend, dtype, method, knob, quantity).  Verdicts:

* ``not comparable``: the case versions differ (the case changed), the number of rays the
  reference flags (``n_not_judged``, left out of the errors) differs, or either side was not
  measured because its run's time budget ran out; for timing also when the
  machines differ (``environment.machine_key``: the rows' own ``machine_key`` where both rows
  record one — a cluster run's rows record their worker's — else the runs') or either side has
  no samples.  A row on one
  side only is ``missing`` (in BASE only) or ``new`` (in NEW only).
* accuracy (deterministic, no statistics): ``worse`` when the new max error exceeds
  ``base·(1 + rtol) + atol`` with ``atol = atol_eps · eps(dtype)`` (so float32 rows get a
  float32-sized slack), when false hits or false misses increase, when more rays are flagged
  (statuses other than CONVERGED and MISS in ``status_counts``: an answer withheld, a miss no
  longer certified, a gradient's or renderer's declined ray, which its error leaves out), when a
  finite error becomes infinite, or when a row that ran now fails or is skipped; ``better``
  symmetrically; else ``same``.
* timing (after asv ``compare`` and pyperf): ``worse``/``better`` only when the ratio of medians
  new/base is beyond ``factor`` (default 1.1) *and* the difference is significant: a one-sided
  Mann–Whitney U test at ``alpha`` (default 0.01) when both sides have ≥ 5 samples; with fewer,
  non-overlapping distribution-free confidence intervals of the medians at level 1 − alpha
  (:func:`median_ci`; with so few samples that is the full sample range).  Else
  ``not significant``.

``python -m bench compare`` exits 1 when any row is accuracy-``worse`` (and timing-``worse`` with
``--timing``; CI compares accuracy only, against a baseline made on another machine), and also
when it would gate fewer rows than BASE holds: rows of BASE ``missing`` in NEW (a truncated or
partial run; ``--allow-missing`` accepts a partial selection on purpose), or either side
incomplete (``complete: "false"`` in its environment.json, or rows not measured because a run's
time budget ran out).  ``new`` rows never fail.  It also fails when fewer than
``--min-comparable`` (default 1: all) of BASE's rows got an accuracy verdict (:func:`coverage`):
a gate that compared nothing (every case version changed) is not a pass.
"""

from __future__ import annotations

import json
from collections.abc import Mapping

import numpy as np
import pandas as pd

from ..run.results import KEY, OVER_BUDGET

ATOL_EPS = 1000.0


def _samples(v) -> np.ndarray:
    if isinstance(v, str) and v:
        return np.asarray(json.loads(v), float)
    return np.zeros(0)


def median_ci(samples: np.ndarray, alpha: float = 0.01) -> tuple[float, float]:
    """Distribution-free confidence interval of the median at level ≥ 1 − alpha from order
    statistics: [x_(k), x_(n−k+1)] with the largest k such that P(Bin(n, ½) < k) ≤ alpha/2
    (Hollander & Wolfe, *Nonparametric statistical methods*, §3.6).  When even k = 1 does not
    reach the level (n < 9 for alpha = 0.01), the sample range, the widest interval the data give."""
    from scipy.stats import binom  # here, not at the top: scipy.stats takes 1.5 s to import

    x = np.sort(np.asarray(samples, float))
    n = x.size
    if n == 0:
        return float("nan"), float("nan")
    k = 0
    while k + 1 <= n // 2 and binom.cdf(k, n, 0.5) <= alpha / 2:  # P(Bin < k+1) = cdf(k)
        k += 1
    k = max(k, 1)
    return float(x[k - 1]), float(x[n - k])


def timing_verdict(base_samples: np.ndarray, new_samples: np.ndarray, factor: float = 1.1,
                   alpha: float = 0.01) -> tuple[str, float, float]:
    """(verdict, median ratio new/base, p-value or NaN)."""
    base_samples, new_samples = np.asarray(base_samples, float), np.asarray(new_samples, float)
    if base_samples.size == 0 or new_samples.size == 0:
        return "not comparable", float("nan"), float("nan")
    ratio = float(np.median(new_samples) / np.median(base_samples))
    if base_samples.size >= 5 and new_samples.size >= 5:
        from scipy.stats import mannwhitneyu  # here: scipy.stats takes 1.5 s to import

        p_slower = mannwhitneyu(new_samples, base_samples, alternative="greater").pvalue
        p_faster = mannwhitneyu(new_samples, base_samples, alternative="less").pvalue
        if ratio > factor and p_slower < alpha:
            return "worse", ratio, float(p_slower)
        if ratio < 1 / factor and p_faster < alpha:
            return "better", ratio, float(p_faster)
        return "not significant", ratio, float(min(p_slower, p_faster))
    lo_b, hi_b = median_ci(base_samples, alpha)
    lo_n, hi_n = median_ci(new_samples, alpha)
    if ratio > factor and lo_n > hi_b:
        return "worse", ratio, float("nan")
    if ratio < 1 / factor and hi_n < lo_b:
        return "better", ratio, float("nan")
    return "not significant", ratio, float("nan")


def _num(v, default=np.nan) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return default
    return f


def same_row_machine(b: Mapping, n: Mapping) -> bool:
    """False when both rows record a machine key and the keys differ (timings measured on
    different machines); True otherwise (the runs' keys decide, :func:`compare`'s
    ``same_machine``)."""
    kb, kn = (str(x.get("machine_key") or "") for x in (b, n))
    kb, kn = ("" if k == "nan" else k for k in (kb, kn))
    return not (kb and kn) or kb == kn


def flagged_rays(status_counts) -> float:
    """Rays of a row's status histogram (``status_counts``, JSON) with a status that does not
    answer them (:data:`bench.studies.stability.ANSWER_STATUSES`, the stability matrix's
    "flagged"); NaN where the row has none."""
    from ..studies.stability import ANSWER_STATUSES, status_histogram

    if not isinstance(status_counts, str) or not status_counts:
        return float("nan")
    return float(sum(n for k, n in status_histogram(status_counts).items() if k not in ANSWER_STATUSES))


def _fewer_answers(b: Mapping, n: Mapping) -> bool:
    """NEW flags more rays than BASE (where both rows have a status histogram)."""
    fb, fn = flagged_rays(b.get("status_counts")), flagged_rays(n.get("status_counts"))
    return bool(np.isfinite(fb) and np.isfinite(fn) and fn > fb)


def accuracy_verdict(b: Mapping, n: Mapping, rtol: float = 0.1, atol_eps: float = ATOL_EPS) -> str:
    if b["outcome"] != "ok":
        return "same" if n["outcome"] == b["outcome"] else ("better" if n["outcome"] == "ok" else "not comparable")
    if n["outcome"] != "ok":
        return "worse"
    eb, en = _num(b["error_max"]), _num(n["error_max"])
    try:
        atol = atol_eps * float(np.finfo(str(n["dtype"])).eps)
    except (TypeError, ValueError):
        atol = 0.0
    fh = (_num(n.get("n_false_hit"), 0) > _num(b.get("n_false_hit"), 0),
          _num(n.get("n_false_miss"), 0) > _num(b.get("n_false_miss"), 0))
    if np.isnan(en) and not np.isnan(eb):
        return "worse"
    if any(fh) or _fewer_answers(b, n) or (np.isfinite(eb) and not np.isfinite(en)) or (
            np.isfinite(en) and en > eb * (1 + rtol) + atol):
        return "worse"
    if _fewer_answers(n, b):
        return "better"
    if (np.isfinite(en) and not np.isfinite(eb)) or (np.isfinite(eb) and eb > en * (1 + rtol) + atol):
        return "better"
    return "same"


def what_changed(b: Mapping, n: Mapping) -> str:
    """The counts that differ between two rows that both ran (false hits, false misses, the
    statuses), ``"false misses 2 → 3; status {…} → {…}"``: what a ``worse`` verdict rests on
    where the maximum error alone does not show it (``inf`` on both sides)."""
    parts = []
    for col, what in (("n_false_hit", "false hits"), ("n_false_miss", "false misses")):
        vb, vn = _num(b.get(col), np.nan), _num(n.get(col), np.nan)
        if not (vb == vn or (np.isnan(vb) and np.isnan(vn))):
            parts.append(f"{what} {vb:g} → {vn:g}")
    sb, sn = (str(x.get("status_counts") or "") for x in (b, n))
    if sb != sn:
        parts.append(f"status {sb} → {sn}")
    return "; ".join(parts)


def compare(base: pd.DataFrame, new: pd.DataFrame, *, factor: float = 1.1, alpha: float = 0.01, rtol: float = 0.1,
            atol_eps: float = ATOL_EPS, same_machine: bool = True) -> pd.DataFrame:
    """One row per key of either side with ``accuracy`` and ``timing`` verdicts (module docstring)."""
    if factor < 1 or not (0 < alpha < 1) or rtol < 0 or atol_eps < 0:
        raise ValueError(f"compare: need factor ≥ 1, 0 < alpha < 1, rtol ≥ 0, atol_eps ≥ 0; "
                         f"got factor={factor}, alpha={alpha}, rtol={rtol}, atol_eps={atol_eps}")
    for name, d in (("BASE", base), ("NEW", new)):
        missing = [k for k in KEY + ["outcome", "error_max", "case_version"] if k not in d.columns]
        if missing:
            raise ValueError(f"{name} results lack columns {missing}; is it an isobench results table?")
    m = base.merge(new, on=KEY, how="outer", suffixes=("_base", "_new"), indicator=True)
    # plain dicts, not ``iterrows``' Series: building two Series a row was 5 of the 7 s that
    # ``bench compare`` took on a quick run's 2,042 rows
    base_cols = {c: c[:-5] for c in m.columns if c.endswith("_base")}
    new_cols = {c: c[:-4] for c in m.columns if c.endswith("_new")}
    rows = []
    for r in m.to_dict("records"):
        key = {k: r[k] for k in KEY}
        if r["_merge"] == "left_only":
            rows.append({**key, "accuracy": "missing", "timing": "missing"})
            continue
        if r["_merge"] == "right_only":
            rows.append({**key, "accuracy": "new", "timing": "new"})
            continue
        b = {short: r[c] for c, short in base_cols.items()} | key
        n = {short: r[c] for c, short in new_cols.items()} | key
        if str(b["case_version"]) != str(n["case_version"]):
            rows.append({**key, "accuracy": "not comparable", "timing": "not comparable",
                         "note": f"case version {b['case_version']} → {n['case_version']}"})
            continue
        if any(str(x.get("reason", "")).startswith(OVER_BUDGET) for x in (b, n)):
            rows.append({**key, "accuracy": "not comparable", "timing": "not comparable",
                         "note": "not measured: over the run's time budget"})
            continue
        nj_b, nj_n = (_num(x.get("n_not_judged"), float("nan")) for x in (b, n))
        if b["outcome"] == "ok" and n["outcome"] == "ok" and (nj_b if np.isfinite(nj_b) else 0) != (
                nj_n if np.isfinite(nj_n) else 0):
            # the reference judges other rays now (bench.run.metrics.judged_rays): errors over different
            # ray sets are not comparable
            rows.append({**key, "accuracy": "not comparable", "timing": "not comparable",
                         "error_base": b.get("error_max"), "error_new": n.get("error_max"),
                         "note": f"rays not judged (the reference flags them) {nj_b:g} → {nj_n:g}"})
            continue
        acc = accuracy_verdict(b, n, rtol, atol_eps)
        machines = same_machine and same_row_machine(b, n)
        if machines and b["outcome"] == "ok" and n["outcome"] == "ok":
            tv, ratio, p = timing_verdict(_samples(b.get("time_samples_s")), _samples(n.get("time_samples_s")),
                                          factor, alpha)
        else:
            tv, ratio, p = "not comparable", float("nan"), float("nan")
        if acc != "worse":
            note = ""
        elif n["outcome"] == "ok":
            note = what_changed(b, n)
        else:
            note = f"now {n['outcome']}: {n.get('reason', '')}"
        if not machines and not note:
            note = "timing measured on different machines"
        rows.append({**key, "accuracy": acc, "error_base": b.get("error_max"), "error_new": n.get("error_max"),
                     "timing": tv, "time_ratio": ratio, "p_value": p, "note": note})
    return pd.DataFrame(rows)


#: accuracy verdicts that compared a row (``missing``, ``new`` and ``not comparable`` did not)
COMPARED = frozenset({"same", "better", "worse"})


def coverage(res: pd.DataFrame, *, allow_missing: bool = False) -> tuple[int, int]:
    """(compared, gated): how many of BASE's rows got an accuracy verdict (:data:`COMPARED`) and
    how many were to be gated — every row of BASE, less those ``missing`` in NEW when
    ``allow_missing`` (a partial selection compared on purpose).  ``new`` rows are not BASE's."""
    acc = res["accuracy"] if len(res) else pd.Series(dtype=str)
    of_base = acc[acc != "new"]
    gated = of_base[of_base != "missing"] if allow_missing else of_base
    return int(gated.isin(COMPARED).sum()), int(len(gated))


def coverage_problem(res: pd.DataFrame, min_share: float = 1.0, *, allow_missing: bool = False) -> str:
    """Why the comparison gated too little ("" when it did not): fewer than ``min_share`` (in
    (0, 1]) of the rows :func:`coverage` counts were compared, or none at all (a comparison of
    nothing never passes, whatever ``min_share``).  Names the count and the commonest reason."""
    if not 0 < min_share <= 1:
        raise ValueError(f"--min-comparable must be a share in (0, 1], got {min_share}")
    compared, gated = coverage(res, allow_missing=allow_missing)
    if gated and compared >= min_share * gated and compared > 0:
        return ""
    acc = res["accuracy"] if len(res) else pd.Series(dtype=str)
    not_cmp = res[acc == "not comparable"]
    why = ""
    if len(not_cmp) and "note" in not_cmp:
        notes = not_cmp["note"].fillna("").astype(str)
        top = notes.str.replace(r"case version .*", "case version changed", regex=True).value_counts()
        if len(top) and top.index[0]:
            why = f"; most not comparable because: {top.index[0]} ({int(top.iloc[0])} rows)"
    share = f"{100 * compared / gated:.1f} %" if gated else "0 %"
    return (f"only {compared} of {gated} rows of BASE were comparable ({share}; required: "
            f"{100 * min_share:g} %){why}: a gate that compares less than that proves nothing. Regenerate BASE "
            "for the changed cases (python -m bench baseline), or pass --min-comparable SHARE to accept fewer")
