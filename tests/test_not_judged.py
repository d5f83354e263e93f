"""Rays the reference flags are *not judged*: never a false hit or miss, never an error of 0 that
reads as fully checked, never a "which to pick" (bench.run.metrics, bench.report.summary, bench.studies.stability,
bench.report.compare)."""

from __future__ import annotations

import json
import types

import numpy as np
import pandas as pd

from bench.studies import stability as S
from bench.report.compare import compare
from bench.run.metrics import judged_rays, root_metrics
from bench.report.summary import NOT_JUDGED, which_to_pick
from impls.protocol import RayResult, Status
from reference import Sphere
from reference import rays as R
from reference.cases import Case, get_case
from reference.numerical import CallableField


def understated_user_case() -> Case:
    """A user's field 10(|x| − 1) declared with L = 1 (true L = 10), a 4×4 camera at (0, 0, 3):
    the reference sees the slope 10 on every ray and flags them all."""
    o, d = R.pinhole(eye=(0.0, 0.0, 3.0), look_at=(0.0, 0.0, 0.0), fov_deg=40.0, width=4, height=4)
    scene = CallableField(lambda x, xp: 10 * (xp.sqrt(xp.sum(x * x, axis=-1)) - 1), lipschitz=1,
                          name="tests.understated_ten_sphere")
    return Case(id="user.understated.4x4", scene=scene, origins=o, directions=d, t_min=0.0, t_max=6.0)


def exact_sphere_result(case) -> RayResult:
    """What a correct method returns: the unit sphere's closed-form hits, CONVERGED or MISS."""
    t = Sphere().first_hit(case.origins, case.directions, case.t_min)
    t = np.where(t <= case.t_max, t, np.inf)
    status = np.where(np.isfinite(t), Status.CONVERGED, Status.MISS)
    return RayResult(t=t, status=status, iterations=np.ones(case.n_rays, int), evals=np.ones(case.n_rays, int))


def test_flagged_reference_rays_are_not_judged():
    case = understated_user_case()
    flagged = np.isnan(case.exact_t)
    assert flagged.all() and np.all(np.isinf(case.exact_t_error_bounds[flagged]))
    np.testing.assert_array_equal(judged_rays(case), ~flagged)
    row = root_metrics(exact_sphere_result(case), case, "float64", {}, {})[0]
    # the correct depths on the flagged rays are neither false hits nor errors; they are counted
    assert row["n_false_hit"] == 0 and row["n_false_miss"] == 0
    assert row["n_not_judged"] == int(flagged.sum()) and row["n_checked"] == case.n_rays - flagged.sum()
    assert row["reference_error_bound"] == 0.0 and np.isnan(row["error_max"])  # nothing checked, not "error 0"


def test_a_surface_colour_on_flagged_rays_is_not_judged_either():
    """The renderers' ``color_vs_surface`` (against the surface image: ρ(x*) at hits, 0 at misses) counts the rays the
    reference flags as root rows do, so a case whose every hit is flagged reads 'not judged' in
    "which to pick", not 'none reached' (a user's field 10× steeper than declared)."""
    from bench.run.metrics import render_metrics
    from impls.methods import get_method

    case = understated_user_case()
    res = exact_sphere_result(case)
    res = RayResult(t=res.t, status=res.status, iterations=res.iterations, evals=res.evals,
                    outputs={"color": np.zeros((case.n_rays, 3))})
    rows = render_metrics(res, case, "float64", {}, {}, get_method("render_surface"))
    (row,) = [r for r in rows if r["quantity"] == "color_vs_surface"]
    assert row["n_not_judged"] == case.n_rays and row["n_checked"] == 0


def test_a_wrong_answer_on_a_judged_ray_still_counts():
    """Judged rays are judged as before: a false hit and a false miss there count."""
    case = types.SimpleNamespace(exact_t=np.array([1.0, np.inf, 2.0, np.nan]),
                                 exact_t_error_bounds=np.array([1e-15, 0.0, np.nan, np.inf]),
                                 judged_mask=np.array([True, True, False, False]))
    res = RayResult(t=np.array([np.inf, 3.0, 2.0, 1.0]),
                    status=np.array([Status.MISS, Status.CONVERGED, Status.CONVERGED, Status.CONVERGED]),
                    iterations=np.ones(4, int), evals=np.ones(4, int))
    row = root_metrics(res, case, "float64", {}, {})[0]
    assert (row["n_false_hit"], row["n_false_miss"], row["n_not_judged"], row["n_checked"]) == (1, 1, 2, 2)
    assert row["error_max"] == np.inf and row["reference_error_bound"] == 1e-15


def test_tangent_rays_are_flagged_unless_proven():
    """An exactly tangent ray float64 cannot certify by a sign change is flagged (NaN bound) —
    unless exact arithmetic proves the touch (torus.tangent: rays in the plane z = r); then it is
    judged with the window bound, √(2δφ r)-sized."""
    case = get_case("csg.complement.inside")  # ray 170: impact parameter exactly 1, a touch of the sphere
    assert np.isnan(case.exact_t_error_bounds[170]) and (~case.judged_mask).sum() == 1
    tangent = get_case("torus.tangent")
    assert tangent.judged_mask.all() and 1e-9 < tangent.exact_t_error_bound < 1e-6
    grazing = get_case("torus.grazing.1e-6")
    assert grazing.judged_mask.all() and 0 < grazing.exact_t_error_bound < 1e-9


def _row(case_id, method, n_not_judged, error_max, n_checked=16, **kw):
    return {"run_id": "r", "case_id": case_id, "case_version": "v", "backend": "numpy", "device": "cpu",
            "dtype": "float64", "method": method, "family": "root", "knob": "", "quantity": "depth",
            "outcome": "ok", "reason": "", "error_max": error_max, "error_max_finite": error_max,
            "n_false_hit": 0, "n_false_miss": 0, "n_not_judged": n_not_judged, "n_checked": n_checked,
            "time_ratio_cf": 1.0, "time_median_s": 1e-3, "evals_per_ray": 3.0,
            "status_counts": json.dumps({"CONVERGED": 16}), **kw}


def test_which_to_pick_never_picks_a_row_with_unjudged_rays():
    df = pd.DataFrame([_row("user.understated.4x4", "sphere_trace", 12, 0.0, n_checked=4),
                       _row("sphere.camera.64x64", "sphere_trace", 0, 1e-13),
                       _row("sphere.camera.64x64", "bisection", 3, 0.0, time_ratio_cf=0.5)])
    picks = which_to_pick(df)
    p = picks[picks["case"] == "user.understated.4x4"]
    assert (p["pick"] == NOT_JUDGED).all() and p["knob"].str.contains("12 ray").all()
    q = picks[(picks["case"] == "sphere.camera.64x64") & (picks["target"] == 1e-12)]
    # the faster bisection row has unjudged rays: the fully checked sphere_trace row is the pick
    assert q["pick"].iloc[0].startswith("sphere_trace")


def test_stability_cell_of_unjudged_rays():
    rows = pd.DataFrame([_row("torus.tangent", "sphere_trace", 256, float("nan"), n_checked=0)])
    cell = S.judge_cell(rows, "float64", scale_of=lambda c: 1.0)
    assert cell["verdict"] == "not judged" and cell["n_not_judged"] == 256
    part = pd.DataFrame([_row("torus.tangent", "sphere_trace", 6, 1e-12, n_checked=250)])
    cell = S.judge_cell(part, "float64", scale_of=lambda c: 1.0)
    assert cell["verdict"] == "survived" and cell["n_not_judged"] == 6
    board = S.scoreboard(pd.DataFrame([{"method": "m", "backend": "numpy", "dtype": "float64", "family": "tangent",
                                        "verdict": "not judged"}]))
    assert int(board["families_total"].iloc[0]) == 0


def test_compare_calls_a_changed_set_of_judged_rays_not_comparable():
    base = pd.DataFrame([_row("torus.tangent", "sphere_trace", float("nan"), 1e-9, n_checked=256)])
    new = pd.DataFrame([_row("torus.tangent", "sphere_trace", 256, float("nan"), n_checked=0)])
    v = compare(base, new, same_machine=False)
    assert v["accuracy"].iloc[0] == "not comparable" and "not judged" in v["note"].iloc[0]
    same = compare(new, new, same_machine=False)
    assert same["accuracy"].iloc[0] == "same"


def test_stand_in_case_without_a_mask_judges_rays_with_an_answer():
    case = types.SimpleNamespace(exact_t=np.array([1.0, np.nan, np.inf]), exact_t_error_bound=0.0)
    np.testing.assert_array_equal(judged_rays(case), [True, False, True])
