"""The comparison logic: accuracy by tolerance per dtype, timing by factor and significance."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from bench.report.compare import compare, median_ci, timing_verdict
from bench.run.results import COLUMNS, to_frame


def test_noise_only_rerun_is_not_significant():
    rng = np.random.default_rng(1)
    a = 1e-3 * (1 + 0.05 * rng.standard_normal(30))
    b = 1e-3 * (1 + 0.05 * rng.standard_normal(30))
    assert timing_verdict(a, b)[0] == "not significant"


def test_real_slowdown_is_worse_and_small_significant_one_is_not():
    rng = np.random.default_rng(2)
    a = 1e-3 * (1 + 0.02 * rng.standard_normal(30))
    assert timing_verdict(a, 1.5 * a[::-1])[0] == "worse"
    assert timing_verdict(a, 1.05 * a[::-1])[0] == "not significant"  # below the factor
    assert timing_verdict(a, a[::-1] / 1.5)[0] == "better"


def test_few_samples_use_non_overlapping_intervals():
    a = np.array([1.0, 1.1, 0.9])
    assert timing_verdict(a, np.array([2.0, 2.1, 1.9]))[0] == "worse"
    assert timing_verdict(a, np.array([1.0, 2.1, 1.9]))[0] == "not significant"


def test_median_ci():
    x = np.arange(1.0, 5.0)
    assert median_ci(x) == (1.0, 4.0)  # too few for 99%: the sample range
    rng = np.random.default_rng(3)
    y = rng.standard_normal(200)
    lo, hi = median_ci(y, 0.01)
    assert y.min() < lo < np.median(y) < hi < y.max()
    # coverage of the true median (0) over many samples is at least about 99%
    cover = np.mean([(lambda a, b: a <= 0 <= b)(*median_ci(rng.standard_normal(40), 0.01)) for _ in range(400)])
    assert cover >= 0.97


def rows(n=6, err=1e-10, dtype="float64", samples=None, seed=0, version="v1"):
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        s = samples if samples is not None else list(1e-3 * (1 + 0.03 * rng.standard_normal(20)))
        out.append({"case_id": f"c{i}", "case_version": version, "backend": "numpy", "dtype": dtype,
                    "method": "m", "knob": "tol=1e-08", "quantity": "depth", "outcome": "ok", "reason": "",
                    "error_max": err, "n_false_hit": 0, "n_false_miss": 0, "time_samples_s": json.dumps(s)})
    return to_frame(out)


def test_planted_accuracy_regression_is_caught():
    base, new = rows(), rows(seed=1)
    new.loc[2, "error_max"] = 1e-7
    res = compare(base, new)
    assert list(res.loc[res["accuracy"] == "worse", "case_id"]) == ["c2"]
    new2 = rows(seed=1)
    new2.loc[4, "n_false_miss"] = 1
    res2 = compare(base, new2)
    assert list(res2.query("accuracy == 'worse'")["case_id"]) == ["c4"]
    # the count the verdict rests on is named (the maximum error alone need not show it)
    assert res2.loc[res2["case_id"] == "c4", "note"].item() == "false misses 0 → 1"
    new3 = rows(seed=1)
    new3.loc[0, ["outcome", "reason", "error_max"]] = ["failed", "RuntimeError: boom", np.nan]
    res3 = compare(base, new3)
    assert res3.loc[res3["case_id"] == "c0", "accuracy"].item() == "worse"
    assert "boom" in res3.loc[res3["case_id"] == "c0", "note"].item()


def test_more_flagged_rays_are_worse_whatever_the_error_of_the_rest():
    """A row that stops answering rays (its misses no longer certified: UNCERTIFIED instead of
    MISS; a gradient's or renderer's rays declined, which its error leaves out) keeps its max error
    or even lowers it: the status histogram is what shows it.  Before, `compare` called such a row
    `same` (or `better`) and passed."""
    base, new = rows(), rows(seed=1)
    base["status_counts"] = json.dumps({"CONVERGED": 700, "MISS": 324})
    new["status_counts"] = json.dumps({"CONVERGED": 700, "MISS": 324})
    new.loc[1, "status_counts"] = json.dumps({"CONVERGED": 700, "UNCERTIFIED": 324})
    new.loc[2, ["status_counts", "error_max"]] = [json.dumps({"CONVERGED": 7, "ILL_CONDITIONED": 693, "MISS": 324}),
                                                  1e-12]
    new.loc[3, "status_counts"] = ""  # a row without a histogram is judged by its errors alone
    res = compare(base, new).set_index("case_id")
    assert list(res.index[res["accuracy"] == "worse"]) == ["c1", "c2"]
    assert "UNCERTIFIED" in res.loc["c1", "note"]
    back = compare(new, base).set_index("case_id")
    assert back.loc["c1", "accuracy"] == "better"  # (c2 back: more rays answered, but its max error grew 100×)


def test_noise_only_rerun_passes():
    base = rows(err=1e-10)
    new = rows(err=1e-10 * (1 + 1e-3), seed=7)  # rounding-level accuracy change, timing noise
    res = compare(base, new)
    assert set(res["accuracy"]) == {"same"}
    assert set(res["timing"]) == {"not significant"}


def test_tolerance_scales_with_the_dtype():
    eps32 = float(np.finfo(np.float32).eps)
    for dtype, verdict in (("float32", "same"), ("float64", "worse")):
        base, new = rows(dtype=dtype, err=1e-6), rows(dtype=dtype, err=1e-6 + 100 * eps32)
        assert set(compare(base, new)["accuracy"]) == {verdict}, dtype


def test_not_comparable_when_case_or_machine_differ():
    res = compare(rows(version="v1"), rows(version="v2"))
    assert set(res["accuracy"]) == {"not comparable"} and set(res["timing"]) == {"not comparable"}
    res = compare(rows(), rows(samples=[1.0] * 20), same_machine=False)
    assert set(res["timing"]) == {"not comparable"} and set(res["accuracy"]) == {"same"}


def test_missing_and_new_rows_are_listed_not_failed():
    base, new = rows(n=3), rows(n=4).iloc[1:]
    res = compare(base, new)
    assert res.set_index("case_id")["accuracy"].to_dict() == {"c0": "missing", "c1": "same", "c2": "same", "c3": "new"}


def test_bad_input_is_a_clear_error():
    with pytest.raises(ValueError, match="factor"):
        compare(rows(), rows(), factor=0.5)
    with pytest.raises(ValueError, match="lack columns"):
        compare(pd.DataFrame({"x": [1]}), rows())
    assert set(COLUMNS) >= {"quantity", "error_ulps_max"}


def test_a_comparison_of_nothing_does_not_pass():
    """Finding 1 of issue 33: every case version changed, so no row was compared; with the
    default rule (all of BASE compared) that is a failure naming the count, never a pass."""
    from bench.report.compare import coverage, coverage_problem

    base, new = rows(version="v1"), rows(version="v2", err=10.0)
    res = compare(base, new)
    assert coverage(res) == (0, 6)
    why = coverage_problem(res)
    assert "only 0 of 6 rows of BASE were comparable" in why and "case version changed (6 rows)" in why
    assert "0 of 6" in coverage_problem(res, 0.01)  # no share lets nothing pass


def test_the_comparable_share_is_a_stated_threshold():
    from bench.report.compare import coverage, coverage_problem

    base = rows(n=10)
    new = rows(n=10, seed=1)
    new.loc[:2, "case_version"] = "v2"  # 3 of 10 cases changed
    res = compare(base, new)
    assert coverage(res) == (7, 10)
    assert "only 7 of 10" in coverage_problem(res)  # default: all
    assert coverage_problem(res, 0.7) == "" and "only 7 of 10" in coverage_problem(res, 0.71)
    # rows missing in NEW count against the share, unless a partial selection is allowed
    res = compare(base, new.iloc[5:])
    assert coverage(res) == (5, 10) and coverage(res, allow_missing=True) == (5, 5)
    assert coverage_problem(res, allow_missing=True) == ""
    assert "0 of 0" in coverage_problem(compare(base, new.iloc[:0]), allow_missing=True)
    with pytest.raises(ValueError, match="--min-comparable"):
        coverage_problem(res, 0.0)
