"""The first-screen summary: counts and "which to pick" on hand-made result frames."""

import math

import pandas as pd

from bench.report import summary


def _row(method="hybrid_secant", backend="numpy", err=1e-10, ratio=5.0, evals=4.0, case="sphere.camera.64x64",
         knob="xtol=1e-12", fh=0, fm=0, outcome="ok", dtype="float64", family="root", quantity="depth"):
    return {"case_id": case, "backend": backend, "dtype": dtype, "method": method, "knob": knob, "family": family,
            "quantity": quantity, "outcome": outcome, "reason": "" if outcome == "ok" else "boom",
            "error_max": err, "time_ratio_cf": ratio, "time_median_s": ratio * 1e-3, "time_iqr_s": 0.0,
            "compile_s": 0.0, "evals_per_ray": evals, "n_false_hit": fh, "n_false_miss": fm}


def test_pick_is_the_fastest_configuration_that_reaches_the_target():
    df = pd.DataFrame([_row(backend="numpy", ratio=9.0), _row(backend="jax:cpu", ratio=3.0),
                       _row(backend="torch:cpu", ratio=1.0, err=1e-5),  # fastest, but only reaches 1e-4
                       _row(method="sphere_trace", backend="numpy", ratio=2.0, err=1e-9)])
    p = summary.which_to_pick(df).set_index("target")
    assert p.loc[1e-4, "pick"] == "hybrid_secant · torch:cpu · float64"
    assert p.loc[1e-8, "pick"] == "sphere_trace · numpy · float64"
    assert p.loc[1e-12, "pick"] == "none reached"
    assert "1e-10" in p.loc[1e-12, "knob"]  # the best error seen is stated
    assert p.loc[1e-8, "candidates"] == 3


def test_a_false_hit_or_miss_disqualifies_whatever_its_error_and_time():
    df = pd.DataFrame([_row(backend="numpy", ratio=0.5, fh=1), _row(backend="torch:cpu", ratio=0.6, fm=2),
                       _row(backend="jax:cpu", ratio=7.0)])
    p = summary.which_to_pick(df, targets=(1e-4, 1e-8))
    assert set(p["pick"]) == {"hybrid_secant · jax:cpu · float64"}


def test_untimed_runs_pick_by_evaluations_and_say_so():
    df = pd.DataFrame([_row(backend="numpy", ratio=math.nan, evals=9.0),
                       _row(method="sphere_trace", ratio=math.nan, evals=3.0)])
    p = summary.which_to_pick(df, targets=(1e-8,))
    assert set(p["by"]) == {"evals"}
    assert set(p["pick"]) == {"sphere_trace · numpy · float64"}
    assert "untimed" in summary.headline(p)[0]


def test_cases_are_not_compared_with_each_other():
    df = pd.DataFrame([_row(case="a.x", ratio=1.0), _row(case="b.y", backend="jax:cpu", ratio=5.0)])
    p = summary.which_to_pick(df, targets=(1e-8,))
    assert dict(zip(p["case"], p["pick"])) == {"a.x": "hybrid_secant · numpy · float64",
                                                "b.y": "hybrid_secant · jax:cpu · float64"}


def test_counts_and_failures_are_per_configuration():
    df = pd.DataFrame([_row(), _row(quantity="other"), _row(backend="jax:cpu", outcome="failed"),
                       _row(backend="torch:cpu", outcome="skipped")])
    assert summary.config_counts(df) == {"ran": 1, "skipped": 1, "failed": 1}
    assert summary.failures(df) == ["sphere.camera.64x64 jax:cpu float64 hybrid_secant @ xtol=1e-12: boom"]
    # a method without knobs (the csv reads its empty knob as NaN) is named without them
    assert summary.failures(pd.DataFrame([_row(knob=float("nan"), outcome="failed")])) == [
        "sphere.camera.64x64 numpy float64 hybrid_secant: boom"]
    ov = summary.overview(df, {"run_id": "r1", "suite": "quick", "complete": "false"})
    assert ov["configurations"] == "1 ran · 1 skipped · 1 failed"
    assert ov["complete"].startswith("NO")


def test_claim_lines_are_cut_between_words_and_say_so():
    long = ("sphere tracing on non-SDF implicit functions with the plain step φ (no Lipschitz bound) terminates "
            "at the first intersection")
    claims = pd.DataFrame([{"id": "5c", "verdict": "holds under conditions", "statement": long,
                            "conditions": "Lipschitz constant ≤ 1"},
                           {"id": "9", "verdict": "fails", "statement": "short", "conditions": "",
                            "counterexample": "x" * 200}])
    lines = summary.claims_lines(claims)
    assert list(lines["id"]) == ["9", "5c"]  # failures first
    cut = lines.set_index("id").loc["5c", "statement"]
    assert len(cut) <= 110 and cut.endswith("…") and long.startswith(cut[:-1]) and long[len(cut) - 1] == " "
    assert lines.set_index("id").loc["9", "statement"] == "short"
    assert len(lines.set_index("id").loc["9", "holds on / counterexample"]) == 160  # one word: cut inside it
    assert summary.clip_words("a b c", 5) == "a b c" and summary.clip_words("alpha beta", 8) == "alpha…"


def test_where_no_configuration_answers_every_ray_a_few_flagged_rays_are_picked_and_counted():
    """At 1024² a certified root finder flags a few grazing rays (UNCERTIFIED): with "every ray
    answered" as the only rule no configuration is picked, and the table answers nothing.  Where
    none answers every ray, the fastest whose only misses are rays it flagged — at most
    FLAGGED_SHARE of them, no silent wrong answer, its answered rays at the target — is picked,
    with the count; a configuration answering every ray still wins, and a silent miss or too many
    flags still disqualify."""
    n = 1 << 20

    def flagged(backend, declined, silent=0, err=1e-10, ratio=1.0):
        r = _row(backend=backend, err=math.inf, ratio=ratio, fm=declined + silent)
        return {**r, "n_miss_declined": declined, "n_rays": n, "error_max_finite": err}

    df = pd.DataFrame([flagged("numpy", 2, ratio=3.0), flagged("jax:cpu", 2, silent=1, ratio=1.0),
                       flagged("torch:cpu", int(2e-2 * n), ratio=0.5), flagged("numba", 2, err=1e-6, ratio=0.1)])
    p = summary.which_to_pick(df, targets=(1e-4, 1e-8)).set_index("target")
    assert p.loc[1e-8, "pick"] == "hybrid_secant · numpy · float64" and p.loc[1e-8, "flagged"] == 2
    assert set(p["by"]) == {"time"}  # ranked by time although no row answers every ray
    assert p.loc[1e-4, "pick"] == "hybrid_secant · numba · float64"  # its answered rays reach 1e-4
    grid = summary.pick_grid(p.reset_index())
    assert "2 ray(s) flagged" in grid.iloc[0]["≤ 1e-08"]
    assert "2 ray(s) flagged" in summary.headline(p.reset_index())[0]
    clean = pd.DataFrame([*df.to_dict("records"), {**_row(backend="warp", ratio=9.0), "n_rays": n}])
    q = summary.which_to_pick(clean, targets=(1e-8,))
    assert q["pick"].iloc[0] == "hybrid_secant · warp · float64" and not (q.get("flagged", pd.Series([0])) > 0).any()


def test_a_configuration_that_declines_rays_is_not_one_that_answers_every_ray():
    """Rays declined with a failure status are left out of the error.  A root finder that never
    certifies a miss (every miss UNCERTIFIED: error 0 there, no false miss) and a normal method
    that declines 99 % of its hits both read as exact and were picked.  They answer fewer rays:
    picked only under FLAGGED_SHARE, with the count, and never before one that answers every ray."""
    n = 65536
    uncertified = {**_row(backend="torch:cpu", ratio=0.1, err=1e-15), "n_miss_declined": 0, "n_declined": 17000,
                   "n_rays": n, "error_max_finite": 1e-15}
    honest = {**_row(backend="numpy", ratio=5.0, err=1e-14), "n_miss_declined": 0, "n_declined": 0, "n_rays": n,
              "error_max_finite": 1e-14}
    few = {**uncertified, "backend": "jax:cpu", "n_declined": 30}
    p = summary.which_to_pick(pd.DataFrame([uncertified, honest, few]), targets=(1e-8,))
    assert p["pick"].iloc[0] == "hybrid_secant · numpy · float64" and not (p.get("flagged", pd.Series([0])) > 0).any()
    q = summary.which_to_pick(pd.DataFrame([uncertified, few]), targets=(1e-8,))
    assert q["pick"].iloc[0] == "hybrid_secant · jax:cpu · float64" and q["flagged"].iloc[0] == 30
    r = summary.which_to_pick(pd.DataFrame([uncertified]), targets=(1e-8,))
    assert r["pick"].iloc[0] == "none reached" and "fewest flagged: 17000 of 65536" in r["knob"].iloc[0]
    grad = dict(family="gradient", quantity="normal_angle", method="normal", knob="")
    decliner = {**_row(backend="torch:cpu", ratio=0.02, err=2e-11, **grad), "n_declined": 48052, "n_rays": n}
    full = {**_row(backend="numpy", ratio=3.0, err=3e-11, **grad), "n_declined": 0, "n_rays": n}
    g = summary.which_to_pick(pd.DataFrame([decliner, full]), targets=(1e-4, 1e-12)).set_index("target")
    assert g.loc[1e-4, "pick"] == "normal · numpy · float64"
    # and the decliner's error is not "the best error seen" when no one reaches the target
    assert g.loc[1e-12, "pick"] == "none reached" and g.loc[1e-12, "knob"] == "best error 3e-11"
    # a case whose every row declined every ray had something to check: 'none reached', not 'nothing to check'
    everything = {**_row(method="dt_finite_diff", err=math.nan, family="param_grad", quantity="dt_dtheta"),
                  "n_checked": 0, "n_declined": 128, "n_rays": 256}
    e = summary.which_to_pick(pd.DataFrame([everything]), targets=(1e-8,))
    assert e["pick"].iloc[0] == "none reached" and "fewest flagged: 128 of 256" in e["knob"].iloc[0]


def test_a_case_with_nothing_to_check_says_so_rather_than_none_reached():
    """dt/dθ of a method that finds its own hits, on a case whose every ray misses: every row
    checked 0 rays (error NaN).  That is not a failure to reach the target ('none reached', as it
    read), it is 'nothing to check'; a row that checked rays and missed the target still reads
    'none reached', and old rows without ``n_checked`` are judged as before."""
    nothing = [dict(_row(method="dt_unrolled", err=math.nan, family="param_grad", quantity="dt_dtheta",
                         case="user.all.miss"), n_checked=0, n_rays=256) for _ in range(2)]
    missed = dict(_row(err=1e-3, case="sphere.camera.64x64"), n_checked=100, n_rays=256)
    p = summary.which_to_pick(pd.DataFrame(nothing + [missed]))
    by_case = {c: g.set_index("target") for c, g in p.groupby("case")}
    assert set(by_case["user.all.miss"]["pick"]) == {summary.NOTHING_TO_CHECK}
    assert by_case["sphere.camera.64x64"].loc[1e-8, "pick"] == "none reached"
    grid = summary.pick_grid(p)
    assert grid.set_index("case").loc["user.all.miss", "≤ 1e-08"].startswith("nothing to check (")
    assert any("user.all.miss → nothing to check" in line for line in summary.headline(p))
    old = summary.which_to_pick(pd.DataFrame([_row(err=math.nan, case="c")]))  # no n_checked column
    assert set(old["pick"]) == {"none reached"}


def test_none_reached_says_whether_the_rays_left_were_flagged_or_wrong():
    """Where every configuration leaves hitting rays unanswered, 'none reached' says whether one
    of them only flagged its rays (no false hit or miss: too many flagged to be picked) and names
    the fewest, or whether every one gave a wrong answer; before, both read 'a false hit/miss'."""
    def row(backend, fm, declined, fh=0, finite=1e-15):
        return {**_row(backend=backend, err=math.inf, fh=fh, fm=fm), "n_miss_declined": declined, "n_rays": 256,
                "error_max_finite": finite}

    flagged = summary.which_to_pick(pd.DataFrame([row("numpy", 30, 30), row("torch:cpu", 10, 10, finite=2e-15),
                                                  row("jax:cpu", 2, 0)]), targets=(1e-8,))
    assert list(flagged["pick"]) == ["none reached"]  # 10 of 256 is more than FLAGGED_SHARE
    why = flagged["knob"].iloc[0]
    assert "fewest flagged: 10 of 256" in why and "no false hit or miss" in why and "torch:cpu" in why, why
    assert "2e-15" in why and "(" not in why, why  # (the headline wraps the reason in parentheses)
    wrong = summary.which_to_pick(pd.DataFrame([row("numpy", 3, 1), row("jax:cpu", 0, 0, fh=2)]), targets=(1e-8,))
    assert list(wrong["pick"]) == ["none reached"]
    assert wrong["knob"].iloc[0] == "every configuration had a false hit or miss or a non-finite depth"
    # a row whose unanswered hits are all flagged, but with a CONVERGED ray of NaN depth, is no honest one
    nan_depth = {**row("numpy", 1, 1), "n_converged_nonfinite": 1}
    assert summary.which_to_pick(pd.DataFrame([nan_depth]), targets=(1e-8,))["knob"].iloc[0] == wrong["knob"].iloc[0]
    # and a row with nothing flagged (its infinite error from elsewhere) is not named as only flagging
    assert summary.which_to_pick(pd.DataFrame([row("numpy", 0, 0)]), targets=(1e-8,))["knob"].iloc[0] == \
        wrong["knob"].iloc[0]
    best = summary.which_to_pick(pd.DataFrame([_row(err=1e-6)]), targets=(1e-8,))
    assert best["knob"].iloc[0] == "best error 1e-06"
