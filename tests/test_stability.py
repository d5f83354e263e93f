"""The stability matrix (bench.studies.stability) on hand-made result frames."""

from __future__ import annotations

import json
import math
import types

import numpy as np
import pandas as pd
import pytest

from bench.studies import stability as S
from bench.run.metrics import root_metrics
from impls.protocol import RayResult, Status

FAMILY = {"g.case": "grazing", "g.case2": "grazing", "u.case": "understated", "t.case": "tangent", "plain": None}
SCALE = {"g.case": 3.0, "g.case2": 3.0, "u.case": 1.3, "t.case": 3.0, "far": 1e6}


def fam(cid):
    return FAMILY.get(cid)


def scale(cid):
    return SCALE.get(cid, 1.0)


def row(case="g.case", method="m", backend="numpy", dtype="float64", family="root", outcome="ok", err=1e-15,
        fh=0, fm=0, declined=0, nonfinite=0, statuses=None, evals=40, iters=20, reason="", **kw):
    statuses = statuses if statuses is not None else {"CONVERGED": 200, "MISS": 56}
    error_max = math.inf if (fh or fm or nonfinite) else err
    return {"case_id": case, "method": method, "backend": backend, "dtype": dtype, "family": family,
            "quantity": "depth", "outcome": outcome, "reason": reason, "error_max": error_max,
            "error_max_finite": err, "n_false_hit": fh, "n_false_miss": fm, "n_miss_declined": declined,
            "n_converged_nonfinite": nonfinite, "status_counts": json.dumps(statuses), "evals_max": evals,
            "iterations_max": iters, **kw}


def cells(rows):
    return S.stability_cells(pd.DataFrame(rows), family_of=fam, scale_of=scale)


def one(rows):
    c = cells(rows)
    assert len(c) == 1
    return c.iloc[0]


def test_clean_cell_survives():
    c = one([row()])
    assert c["verdict"] == "survived" and c["mark"] == "✓"
    assert c["error_max"] == 1e-15 and c["evals_max"] == 40 and c["statuses"] == {"CONVERGED": 200, "MISS": 56}


def test_planted_silent_false_miss_fails():
    # the understated-L outcome on a branch without LIPSCHITZ_VIOLATED: every hitting ray MISS
    c = one([row(case="u.case", fm=256, statuses={"MISS": 256})])
    assert c["verdict"] == "failed" and c["n_false_miss"] == 256 and c["mark"] == "✗"
    assert any("reported MISS" in r for r in c["reasons"])


def test_planted_flagged_cell_counts_as_survived():
    # the same rays declined with LIPSCHITZ_VIOLATED: metrics counts them in n_false_miss, but
    # they are declined (n_miss_declined), so nothing is silently wrong
    c = one([row(case="u.case", fm=256, declined=256, statuses={"LIPSCHITZ_VIOLATED": 256}, err=float("nan"))])
    assert c["verdict"] == "flagged" and c["mark"] == "⚑" and c["n_false_miss"] == 0 and c["n_flagged"] == 256
    assert S.survived(c["verdict"])


def test_flagged_and_one_silent_miss_fails():
    c = one([row(fm=11, declined=10, statuses={"CONVERGED": 100, "MAX_ITER": 10, "MISS": 146})])
    assert c["verdict"] == "failed" and c["n_false_miss"] == 1 and c["n_flagged"] == 10


def test_old_rows_without_declined_column_count_every_false_miss_as_silent():
    r = row(fm=3, statuses={"CONVERGED": 100, "MAX_ITER": 3, "MISS": 153})
    del r["n_miss_declined"], r["n_converged_nonfinite"]
    assert one([r])["verdict"] == "failed"


def test_false_hit_fails():
    assert one([row(fh=1)])["verdict"] == "failed"


def test_converged_error_over_the_dtype_scaled_tolerance_fails():
    tol64 = math.sqrt(np.finfo(np.float64).eps) * 3.0
    assert one([row(err=0.9 * tol64)])["verdict"] == "survived"
    c = one([row(err=1.1 * tol64)])
    assert c["verdict"] == "failed" and c["n_over_tol"] == 1 and c["tolerance"] == pytest.approx(tol64)
    # the same error is within float32's tolerance
    assert one([row(err=1.1 * tol64, dtype="float32")])["verdict"] == "survived"


def test_tolerance_scales_with_the_case_depth():
    assert S.depth_tolerance("float64", 1e6) == pytest.approx(1e6 * S.depth_tolerance("float64", 1.0))
    assert S.depth_tolerance("float64", 1e-6) == S.depth_tolerance("float64", 1.0)  # floored at 1
    assert S.depth_tolerance("float32", 1.0) > 1e3 * S.depth_tolerance("float64", 1.0)


def test_tolerance_is_capped_at_a_quarter_of_the_scene():
    """On sphere.far.1e6 in float32 the two terms allow 357 for a sphere of diameter 2: a CONVERGED
    answer on its far side counted as survived (probe of 2026-11-30).  Capped at S/4."""
    assert S.catalog_size("sphere.far.1e6") == pytest.approx(2.0)
    far = dict(scale_of=S.catalog_scale, origin_of=S.catalog_origin_norm, size_of=S.catalog_size)
    for dt in ("float32", "float64"):
        wrong = S.judge_cell([row(case="sphere.far.1e6", err=2.0, dtype=dt)], dt, **far)
        assert wrong["verdict"] == "failed" and wrong["tolerance"] == pytest.approx(min(0.5, wrong["tolerance"]))
    assert S.judge_cell([row(case="sphere.far.1e6", err=0.1, dtype="float32")], "float32", **far)["verdict"] == "survived"
    assert S.depth_tolerance("float32", 1e6, 1e6, 2.0) == 0.5
    assert S.depth_tolerance("float64", 3.0, 3.0, 2.0) == S.depth_tolerance("float64", 3.0, 3.0)  # (far below the cap)


def test_converged_nonfinite_fails():
    assert one([row(nonfinite=1)])["verdict"] == "failed"
    r = row(err=float("nan"))  # an old row: inf max error explained by no false hit or miss
    r["error_max"] = math.inf
    del r["n_converged_nonfinite"]
    assert one([r])["verdict"] == "failed"


def test_failed_configuration_fails_and_skipped_only_is_na():
    assert one([row(), row(case="g.case2", outcome="failed", reason="RuntimeError: boom")])["verdict"] == "failed"
    c = one([row(outcome="skipped", reason="not implemented")])
    assert c["verdict"] == "n/a" and c["mark"] == "—" and "not implemented" in c["reasons"][0]


def test_cells_group_cases_of_a_family_and_ignore_other_rows():
    rows = [row(err=1e-16, evals=30), row(case="g.case2", err=2e-16, evals=90, statuses={"CONVERGED": 5}),
            row(case="plain"), row(family="gradient"), row(quantity="normal_angle")]
    rows[-1]["quantity"] = "normal_angle"
    c = one(rows)
    assert c["error_max"] == 2e-16 and c["evals_max"] == 90 and c["statuses"]["CONVERGED"] == 205
    assert c["cases"] == ["g.case", "g.case2"]


def test_scoreboard_and_matrix():
    rows = []
    for b in ("numpy", "jax"):
        for dt in ("float64", "float32"):
            rows.append(row(backend=b, dtype=dt))
            rows.append(row(case="t.case", backend=b, dtype=dt, statuses={"CONVERGED": 250, "MAX_ITER": 6}))
            bad = b == "jax" and dt == "float32"
            rows.append(row(case="u.case", backend=b, dtype=dt, fm=256 if bad else 0, statuses={"MISS": 256} if bad
                            else {"CONVERGED": 256}))
    c = cells(rows)
    board = S.scoreboard(c)
    board = board.set_index([board["backend"], board["dtypes"].map(lambda d: d[0])])
    for dt in ("float64", "float32"):  # per backend and dtype
        assert board.loc[("numpy", dt), "families_survived"] == 3 and board.loc[("numpy", dt), "families_total"] == 3
        assert board.loc[("numpy", dt), "cells_flagged"] == 1
    assert board.loc[("jax", "float64"), "families_survived"] == 3
    assert board.loc[("jax", "float32"), "families_survived"] == 2
    assert board.loc[("jax", "float32"), "failed_families"] == ["understated"]
    assert board.loc[("jax", "float32"), "cells_survived"] == 2 and board.loc[("jax", "float32"), "cells_total"] == 3
    lines = S.scoreboard_lines(S.scoreboard(c))
    assert lines[0].startswith("jax (float64): 3/3 families survived")  # float64 first, then float32
    assert any(line.startswith("jax (float32): 2/3 families survived") and "failed: understated" in line for line in lines)
    m = S.stability_matrix(c)
    assert list(m.columns) == ["method", "backend", "dtype", "understated", "tangent", "grazing"]  # catalog order
    assert len(m) == 4
    jax32 = m[(m["backend"] == "jax") & (m["dtype"] == "float32")].iloc[0]
    assert jax32["understated"].startswith("✗") and jax32["tangent"].startswith("⚑")
    assert jax32["grazing"] == "✓ 1e-15 · 40"
    assert list(zip(m["backend"], m["dtype"])) == [("jax", "float64"), ("numpy", "float64"), ("jax", "float32"),
                                                   ("numpy", "float32")]
    md = S.stability_matrix(c, detail=True)
    text, detail = md.iloc[0]["tangent"]
    assert "MAX_ITER 6" in detail and "flagged rays 6" in detail


def test_empty_and_non_root_frames():
    assert S.stability_cells(pd.DataFrame()).empty
    assert cells([row(family="render")]).empty
    assert S.scoreboard(cells([])).empty
    assert S.stability_matrix(cells([])).empty


def test_catalog_families_and_scales():
    assert S.catalog_family("shell.understated.L10") == "understated"
    assert S.catalog_family("box.parallel") == "parallel"  # also tagged grazing: the most specific wins
    assert S.catalog_family("sphere.camera.64x64") is None
    assert S.catalog_family("no.such.case") is None
    assert S.catalog_scale("sphere.far.1e6") > 9e5
    # the origins' magnitude counts too, as rounding: box.parallel's rays start 3.29 from the origin
    assert S.catalog_scale("box.parallel") == pytest.approx(2.0)
    assert S.catalog_origin_norm("box.parallel") == pytest.approx(3.288, abs=1e-3)
    eps32 = float(np.finfo(np.float32).eps)
    assert S.depth_tolerance("float32", 2.7, 1e4) == pytest.approx(np.sqrt(eps32) * 2.7 + 100 * eps32 * 1e4)


def test_metrics_separate_declined_rays_from_reported_misses():
    exact = np.array([1.0, 2.0, 3.0, np.inf, 5.0])
    case = types.SimpleNamespace(exact_t=exact, exact_t_error_bound=0.0)
    res = RayResult(t=np.array([1.0, np.nan, np.inf, np.inf, np.nan]),
                    status=np.array([Status.CONVERGED, Status.MAX_ITER, Status.MISS, Status.MISS, Status.CONVERGED]),
                    iterations=np.zeros(5, int), evals=np.zeros(5, int))
    r = root_metrics(res, case, "float64", {}, {})[0]
    assert r["n_false_miss"] == 2 and r["n_miss_declined"] == 1 and r["n_converged_nonfinite"] == 1
    c = one([{**row(), **r, "status_counts": json.dumps(res.status_counts())}])
    assert c["verdict"] == "failed" and c["n_false_miss"] == 1 and c["n_nonfinite"] == 1 and c["n_flagged"] == 1


def test_scoreboard_of_a_backend_with_no_judged_cell():
    """A plugged backend whose every cell was skipped: no crash (it broke the report), and a line
    that says no cell was judged rather than a 0/0 score."""
    c = pd.DataFrame([{"method": "sphere_trace", "backend": "fake", "dtype": "float64", "family": "grazing",
                       "verdict": "n/a"}])
    board = S.scoreboard(c)
    assert board.loc[0, "families_survived"] == 0 and board.loc[0, "families_total"] == 0
    assert S.scoreboard_lines(board)[0].startswith("fake (float64): no judged cell")
