"""The runner's generic machinery, on a fake backend with fake methods of every family.

Checks: every planned configuration yields rows (ok, skipped with a reason, or failed with the
error); the metrics measure exactly the error the fake methods plant; failures (exception, wrong
shape, silent NaN, timeout) become rows and the run goes on; sweeps derive from the knobs;
backends interleave.
"""

from __future__ import annotations

import dataclasses
import json
import time

import numpy as np
import pytest

import impls.methods
from bench.run import configuration, runner
from bench.run import plan as planning
from bench.run.results import read_results
from bench.run.suites import Suite, default_sweep
from bench.run.timing import TimingPolicy
from impls import METHODS, Unavailable
from impls.methods import Knob, MethodSpec
from reference import Sphere, get_case
from reference.cases import Case
from tests.test_bench_fakes import FAKE_METHODS, PLANTED, FakeBackend

CASE = "sphere.camera.64x64"
FAST = TimingPolicy(min_repeats=1, min_time_s=0.0, min_sample_s=0.0, warmup=0, timeout_s=5.0)


@pytest.fixture
def fake_methods(monkeypatch):
    """METHODS with the fake methods added (the dict object itself, as every module holds it)."""
    for name, spec in FAKE_METHODS.items():
        monkeypatch.setitem(METHODS, name, spec)
    return METHODS


def suite(methods, sweeps=None) -> Suite:
    return Suite(name="test", case_pattern=CASE, dtypes=("float64",), sweeps=sweeps or {}, methods=tuple(methods))


def rows_of(cfg, backend, policy=FAST):
    return configuration.run_one("r", cfg, backend, policy, cf_time=1.0)


def test_each_family_measures_the_planted_error(fake_methods):
    case = get_case(CASE)
    b = FakeBackend()
    got = {}
    for m in ("fake_root", "fake_normal", "fake_dt"):
        knobs = {k.name: k.default for k in FAKE_METHODS[m].knobs}
        for r in rows_of(runner.Config(case, "fake", m, "float64", knobs), b):
            assert r["outcome"] == "ok", r
            got[r["quantity"]] = r
    assert got["depth"]["error_max"] == pytest.approx(PLANTED * (1 + 1e-6), rel=1e-6)
    assert got["depth"]["n_false_hit"] == 0 and got["depth"]["n_false_miss"] == 0
    assert got["normal_angle"]["error_max"] == pytest.approx(PLANTED, rel=1e-4)
    assert got["normal_angle"]["unit"] == "rad"
    assert got["curvature_laplacian"]["error_max"] == pytest.approx(PLANTED, rel=1e-6)
    # dt/dθ: 4 parameters each off by PLANTED → norm 2·PLANTED; the declined grazing ray is left out
    assert got["dt_dtheta"]["error_max"] == pytest.approx(2 * PLANTED, rel=1e-6)
    assert got["dt_dtheta"]["n_declined"] == 1
    assert got["dt_dtheta"]["n_checked"] == int(np.isfinite(case.exact_t).sum()) - 1
    assert json.loads(got["dt_dtheta"]["status_counts"])["ILL_CONDITIONED"] == 1
    # evaluations per ray come from the method's counts
    assert got["normal_angle"]["evals_per_ray"] == 4 and got["depth"]["evals_max"] == 9


def test_render_without_a_reference_is_skipped_with_the_reason(fake_methods, monkeypatch):
    # every catalog case has a colour field now, so take it away to see the skip path
    from bench.run import references

    def no_colour(case):
        raise references.NotApplicable(f"{case.id} has no colour field ρ (case.color_field)")

    from bench.run import metrics

    monkeypatch.setattr(references, "color_field", no_colour)
    monkeypatch.setattr(metrics, "color_field", no_colour)
    case = get_case(CASE)
    rows = rows_of(runner.Config(case, "fake", "fake_render", "float64", {"n_samples": 8}), FakeBackend())
    assert rows and all(r["outcome"] == "skipped" for r in rows)
    assert any("colour" in r["reason"] for r in rows)


@pytest.mark.parametrize("behaviour, message", [(1, "planted failure"), (2, "wrong shape"), (3, "silent NaN")])
def test_failures_become_rows(fake_methods, behaviour, message):
    case = get_case(CASE)
    cfg = runner.Config(case, "fake", "fake_root", "float64", {"tol": 1e-6, "max_steps": 8, "behaviour": behaviour})
    (r,) = rows_of(cfg, FakeBackend())
    assert r["outcome"] == "failed" and message in r["reason"], r["reason"]


def test_a_hang_becomes_a_timeout_row(fake_methods):
    case = get_case(CASE)
    cfg = runner.Config(case, "fake", "fake_root", "float64", {"tol": 1e-6, "max_steps": 8, "behaviour": 4})
    (r,) = rows_of(cfg, FakeBackend(), dataclasses.replace(FAST, timeout_s=0.3))
    assert r["outcome"] == "failed" and "time limit" in r["reason"]


def test_skip_reasons_name_what_is_missing(fake_methods):
    case = get_case(CASE)
    knobs = {"tol": 1e-6, "max_steps": 8, "behaviour": 0}
    cfg = runner.Config(case, "gone", "fake_root", "float64", knobs)
    (r,) = rows_of(cfg, Unavailable("gone", "not installed"))
    assert r["outcome"] == "skipped" and "unavailable: not installed" in r["reason"]
    (r,) = rows_of(cfg, FakeBackend(methods=("fake_dt",)))
    assert "does not implement fake_root" in r["reason"]
    (r,) = rows_of(dataclasses.replace(cfg, dtype="float32"), FakeBackend())
    assert "does not support float32" in r["reason"]

    class NoLipschitz(Sphere):
        @property
        def info(self):
            return dataclasses.replace(Sphere.info.fget(self), lipschitz=None)

    nolip = Case(id="nolip", scene=NoLipschitz(), origins=case.origins, directions=case.directions)
    (r,) = rows_of(dataclasses.replace(cfg, case=nolip), FakeBackend())
    assert r["outcome"] == "skipped" and "lipschitz" in r["reason"]

    class NoNormals(Sphere):
        def normal_exact(self, x):
            raise NotImplementedError("no normals here")

    nonorm = Case(id="nonorm", scene=NoNormals(), origins=case.origins, directions=case.directions)
    rows = rows_of(runner.Config(nonorm, "fake", "fake_normal", "float64", {"n_fd": 4}), FakeBackend())
    by_q = {r["quantity"]: r for r in rows}
    assert by_q["normal_angle"]["outcome"] == "skipped" and "no normals here" in by_q["normal_angle"]["reason"]
    assert by_q["curvature_laplacian"]["outcome"] == "ok"  # the other quantity is still checked


def test_a_run_keeps_every_planned_configuration(fake_methods, tmp_path):
    backends = {"fake": FakeBackend(), "fake2": FakeBackend("fake2", methods=("fake_root",)),
                "gone": Unavailable("gone", "not installed")}
    s = suite(["fake_root", "fake_normal", "fake_dt", "fake_render"],
              sweeps={"fake_root": [{"tol": 1e-6, "max_steps": 8, "behaviour": b} for b in (0, 1, 3)]})
    cfgs = runner.plan(s, list(backends), None, None, None)
    df = runner.run(s, backends, tmp_path, policy=FAST)
    keys = set(map(tuple, df[runner.CONFIG_KEY].astype(str).itertuples(index=False, name=None)))
    assert keys == {tuple(map(str, c.key)) for c in cfgs}  # nothing disappears
    assert (df["outcome"] == "failed").sum() == 2 * 2  # behaviours 1 and 3 on two backends
    assert set(df.loc[df["backend"] == "gone", "outcome"]) == {"skipped"}
    assert set(df.loc[(df["backend"] == "fake2") & (df["method"] != "fake_root"), "outcome"]) == {"skipped"}
    back = read_results(tmp_path)
    assert len(back) == len(df)
    env = json.loads((tmp_path / "environment.json").read_text())
    assert env["complete"] == "true" and env["backend.fake.fake"] == "1"


def test_backends_interleave_and_rotate(fake_methods):
    s = suite(["fake_root"])
    cfgs = runner.plan(s, ["a", "b", "c"], None, None, None)
    n_knobs = len(default_sweep(FAKE_METHODS["fake_root"], "quick"))
    assert len(cfgs) == 3 * n_knobs
    firsts = [cfgs[3 * k].backend_id for k in range(n_knobs)]
    assert firsts[:3] == ["a", "b", "c"]
    for k in range(n_knobs):  # each knob setting runs on every backend back to back
        assert {c.backend_id for c in cfgs[3 * k: 3 * k + 3]} == {"a", "b", "c"}
        assert len({json.dumps(c.knobs, sort_keys=True) for c in cfgs[3 * k: 3 * k + 3]}) == 1


def test_bad_selection_is_a_clear_error(fake_methods):
    with pytest.raises(ValueError, match="--method: unknown method"):
        runner.plan(suite(["fake_root"]), ["a"], None, ["nosuch"], None)
    with pytest.raises(ValueError, match="--dtype"):
        runner.plan(suite(["fake_root"]), ["a"], None, None, ["float63"])


def test_method_globs_select_as_case_globs_do(fake_methods):
    """``--method`` takes globs as ``--case`` does ('volume_*'); a glob that matches no method is
    the same clear error as an unknown name."""
    s = suite(["fake_root", "fake_normal", "fake_dt"])
    got = {c.method for c in runner.plan(s, ["a"], None, ["fake_n*", "fake_dt"], None)}
    assert got == {"fake_normal", "fake_dt"}
    with pytest.raises(ValueError, match=r"--method: unknown method\(s\) \['fake_zz\*'\]"):
        runner.plan(s, ["a"], None, ["fake_root", "fake_zz*"], None)


def test_default_sweep_derives_from_knobs():
    spec = MethodSpec("m", "render", (Knob("tol", 1e-8, float, 0.0, "t", role="tolerance"), Knob("n_samples", 64, int, 1, "n", role="budget"),
                                      Knob("sharpness", 50.0, float, 0.0, "s", role="setting")), (), "")
    sw = default_sweep(spec, "quick")
    assert all(set(k) == {"tol", "n_samples", "sharpness"} for k in sw)
    assert all(k["sharpness"] == 50.0 for k in sw)  # not a tolerance, no sweep hint: fixed
    tols = sorted({k["tol"] for k in sw if k["n_samples"] == 64})
    assert tols == [1e-12, 1e-8, 1e-4]  # the report's error targets
    budget = sorted(k["n_samples"] for k in sw if k["tol"] == min(tols))
    assert len(budget) >= 3 and budget[-1] == 64 and budget[0] < 64
    full = default_sweep(spec, "full")
    assert len(full) > len(sw) and max(k["n_samples"] for k in full) == 256
    assert len({json.dumps(k, sort_keys=True) for k in full}) == len(full)  # no duplicates
    # xtol is a tolerance; a seed is not a budget
    spec2 = MethodSpec("m2", "render", (Knob("xtol", 1e-12, float, 0.0, "x", role="tolerance"), Knob("seed", 0, int, 0, "seed", role="seed"),
                                        Knob("n_coarse", 32, int, 1, "n", role="budget")), (), "")
    sw2 = default_sweep(spec2, "quick")
    assert {k["seed"] for k in sw2} == {0}
    assert sorted({k["xtol"] for k in sw2}) == [1e-12, 1e-8, 1e-4]
    assert len({k["n_coarse"] for k in sw2}) == 3
    # an explicit hint wins
    hinted = dataclasses.replace(spec, knobs=spec.knobs[:2] + (
        Knob("sharpness", 50.0, float, 0.0, "s", role="setting", sweep=(10.0, 100.0)),))
    assert {k["sharpness"] for k in default_sweep(hinted)} == {50.0, 10.0, 100.0}
    # the real catalog: every method gets a non-empty sweep whose knobs validate
    for m in impls.methods.METHODS.values():
        for k in default_sweep(m, "quick"):
            m.validate(k)


def test_budget_skips_the_rest_visibly_and_resume_finishes(fake_methods, tmp_path):
    backends = {"fake": FakeBackend()}
    s = suite(["fake_root", "fake_normal"], sweeps={"fake_root": [{"tol": 1e-6, "max_steps": m, "behaviour": 0}
                                                                  for m in (2, 4, 8)]})
    df = runner.run(s, backends, tmp_path, policy=FAST, budget_s=0.0)
    over = df["reason"].fillna("").str.startswith(runner.OVER_BUDGET)
    assert over.sum() >= len(runner.plan(s, ["fake"], None, None, None)) - 1
    assert set(df.loc[over, "outcome"]) == {"skipped"}
    df2 = runner.run(s, backends, tmp_path, policy=FAST, resume=True)
    assert set(df2["outcome"]) == {"ok"}
    assert not df2.duplicated(["case_id", "backend", "dtype", "method", "knob", "quantity"]).any()


def test_nothing_runs_that_cannot_be_checked(fake_methods):
    case = get_case(CASE)

    class NoAnswers(Sphere):
        @property
        def info(self):
            return dataclasses.replace(Sphere.info.fget(self), exact_normals=False, exact_curvature=False)

    c = Case(id="noanswers", scene=NoAnswers(), origins=case.origins, directions=case.directions)
    b = FakeBackend()
    (r,) = rows_of(runner.Config(c, "fake", "fake_normal", "float64", {"n_fd": 4}), b)
    assert r["outcome"] == "skipped" and "exact_normals=False" in r["reason"] and "exact_curvature=False" in r["reason"]
    assert b.calls == []  # skipped before running


def test_rounds_pool_samples_from_later_passes(fake_methods, tmp_path):
    b = FakeBackend()
    s = suite(["fake_root"], sweeps={"fake_root": [{"tol": 1e-6, "max_steps": 8, "behaviour": 0}]})
    pol = dataclasses.replace(FAST, min_repeats=3)
    df = runner.run(s, {"fake": b}, tmp_path, policy=pol, rounds=3)
    (r,) = df.to_dict("records")
    samples = json.loads(r["time_samples_s"])
    assert r["rounds"] == 3 and r["n_samples"] == len(samples) >= 9
    assert r["time_median_s"] == pytest.approx(float(np.median(samples)))
    assert json.loads((tmp_path / "environment.json").read_text())["rounds"] == "3"
    with pytest.raises(ValueError, match="--rounds"):
        runner.run(s, {"fake": b}, tmp_path / "x", policy=pol, rounds=0)


def fake_rendering(monkeypatch, render_exact):
    import sys
    import types

    import reference

    mod = types.ModuleType("reference.rendering")
    mod.render_exact, mod.MODELS = render_exact, ("nerf", "unisurf", "neus", "volsdf")
    monkeypatch.setitem(sys.modules, "reference.rendering", mod)
    monkeypatch.setattr(reference, "rendering", mod, raising=False)
    return mod


def colored_case():
    from tests.test_bench_fakes import FakeColor

    base = get_case(CASE)
    case = Case(id="colored", scene=base.scene, origins=base.origins, directions=base.directions)
    object.__setattr__(case, "color_field", FakeColor())
    return case


def test_costly_render_reference_is_cached_on_disk_limited_in_time_and_optional(fake_methods, monkeypatch, tmp_path):
    from bench.run.references import ReferenceOptions
    from tests.test_bench_fakes import FakeColor, fake_render_exact

    calls = []

    def counting(*a, **k):
        calls.append(a[2])
        if a[2] == "neus":  # a reference that would take minutes
            import time

            deadline = time.perf_counter() + 30
            while time.perf_counter() < deadline:
                pass
        return fake_render_exact(*a, **k)

    fake_rendering(monkeypatch, counting)
    case, b, knobs = colored_case(), FakeBackend(), {"n_samples": 8, "sharpness": 50.0}
    cfg = runner.Config(case, "fake", "volume_nerf_uniform", "float64", knobs)

    def integral(cache):
        rows = configuration.run_one("r", cfg, b, FAST, 1.0, cache)
        return next(r for r in rows if r["quantity"] == "color_vs_integral")

    opts = ReferenceOptions(timeout_s=0.5, disk=tmp_path / "refcache")
    first = integral({"_options": opts})
    second = integral({"_options": opts})  # a new run: from disk
    assert first["outcome"] == "ok", first
    assert calls == ["nerf"] and first["error_max"] == second["error_max"] and first["outcome"] == "ok"
    assert len(list((tmp_path / "refcache").glob("*.npz"))) == 1
    skipped = integral({"_options": ReferenceOptions(expensive=False)})
    assert skipped["outcome"] == "skipped" and "--suite full" in skipped["reason"]
    monkeypatch.setitem(FAKE_METHODS, "volume_neus_uniform",
                        dataclasses.replace(FAKE_METHODS["volume_nerf_uniform"], name="volume_neus_uniform"))
    monkeypatch.setitem(METHODS, "volume_neus_uniform", FAKE_METHODS["volume_neus_uniform"])
    import tests.test_bench_fakes as fakes

    monkeypatch.setitem(fakes._IMPL, "volume_neus_uniform", fakes.fake_volume)
    cfg, b = runner.Config(case, "fake", "volume_neus_uniform", "float64", knobs), FakeBackend()
    run_cache = {"_options": opts}
    slow = integral(run_cache)
    assert slow["outcome"] == "skipped" and "took longer than 0.5 s" in slow["reason"]
    n_calls = len(calls)
    # the same case and density at another sharpness, same run: not attempted again
    cfg = runner.Config(case, "fake", "volume_neus_uniform", "float64", {**knobs, "sharpness": 60.0})
    again = integral(run_cache)
    assert len(calls) == n_calls and "not attempted again" in again["reason"]
    # another case, same run: attempted (a slow case does not cost the others their reference)
    case = dataclasses.replace(case, id="colored2")
    object.__setattr__(case, "color_field", FakeColor())
    cfg = runner.Config(case, "fake", "volume_neus_uniform", "float64", knobs)
    other = integral(run_cache)
    assert len(calls) == n_calls + 1 and "took longer than 0.5 s" in other["reason"]


def test_render_family_against_the_integral_and_the_surface_colour(fake_methods, monkeypatch):
    from tests.test_bench_fakes import FakeColor, fake_render_exact

    fake_rendering(monkeypatch, fake_render_exact)
    base = get_case(CASE)
    case = Case(id="colored", scene=base.scene, origins=base.origins, directions=base.directions)
    object.__setattr__(case, "color_field", FakeColor())
    b = FakeBackend()
    knobs = {"n_samples": 8, "sharpness": 50.0}
    by_q = {r["quantity"]: r for r in rows_of(runner.Config(case, "fake", "volume_nerf_uniform", "float64", knobs), b)}
    integral, surface = by_q["color_vs_integral"], by_q["color_vs_surface"]
    assert integral["outcome"] == "ok" and integral["error_max"] == pytest.approx(np.sqrt(3) * PLANTED, rel=1e-6)
    assert integral["reference_error_bound"] == pytest.approx(1e-11)
    # against the surface image (ρ(x*) at hits, 0 at misses): the blur 1/s at the hits dominates the
    # planted error on the misses; every ray is checked
    hit = np.isfinite(base.exact_t)
    rho = FakeColor().value(base.origins[hit] + base.exact_t[hit, None] * base.directions[hit])
    want = np.max(np.linalg.norm(rho / 50.0 - PLANTED, axis=1))
    assert surface["outcome"] == "ok" and surface["error_max"] == pytest.approx(want, rel=1e-9)
    assert surface["n_checked"] == base.n_rays and (~hit).any()
    by_q = {r["quantity"]: r for r in rows_of(runner.Config(case, "fake", "volume_unisurf_uniform", "float64", knobs),
                                               b)}
    assert by_q["color_vs_integral"]["outcome"] == "skipped"
    assert "no continuous reference for unisurf" in by_q["color_vs_integral"]["reason"]
    assert by_q["color_vs_surface"]["outcome"] == "ok"


def _plan_on(monkeypatch, cases, s):
    """The plan of suite ``s`` over exactly ``cases`` on one backend."""
    monkeypatch.setattr(planning, "select_cases", lambda suite, pattern: cases)
    return runner.plan(s, ["a"], None, None, None)


def test_plan_limits_cases_and_puts_defaults_first(fake_methods, monkeypatch):
    case = get_case(CASE)

    class NoLipschitz(Sphere):
        @property
        def info(self):
            return dataclasses.replace(Sphere.info.fget(self), lipschitz=None)

    cases = [Case(id=f"c{i}", scene=Sphere() if i != 1 else NoLipschitz(), origins=case.origins,
                  directions=case.directions) for i in range(4)]
    s = dataclasses.replace(suite(["fake_root"]), sweep_cases=1, max_cases=2)
    cfgs = _plan_on(monkeypatch, cases, s)
    sweep = s.sweep_for(FAKE_METHODS["fake_root"])
    by_case = {c.id: [x for x in cfgs if x.case.id == c.id] for c in cases}
    assert len(by_case["c0"]) == len(sweep)  # the sweep on the first applicable case
    assert len(by_case["c1"]) == 1  # not applicable: one configuration, to be skipped with the reason
    assert len(by_case["c2"]) == 1  # second applicable case: defaults only
    assert by_case["c3"] == []  # beyond max_cases
    defaults = {json.dumps(sweep[0], sort_keys=True)}
    n_first = 3  # c0, c1, c2 defaults come before any sweep point
    assert all(json.dumps(c.knobs, sort_keys=True) in defaults for c in cfgs[:n_first])
    assert all(json.dumps(c.knobs, sort_keys=True) not in defaults for c in cfgs[n_first:])


def test_plan_spreads_cases_over_scene_families_and_limits_secondary_dtypes(fake_methods, monkeypatch):
    case = get_case(CASE)
    ids = ["sphere.a", "sphere.b", "sphere.lead", "torus.a", "torus.b", "csg.a"]
    cases = [Case(id=i, scene=Sphere(), origins=case.origins, directions=case.directions) for i in ids]
    s = dataclasses.replace(suite(["fake_root"]), sweep_cases=1, max_cases=3, diverse_cases=True,
                            lead_cases={"*": ("nosuch", "sphere.lead")}, dtypes=("float64", "float32"),
                            secondary_dtype_cases=1)
    cfgs = _plan_on(monkeypatch, cases, s)
    used = list(dict.fromkeys(c.case.id for c in cfgs if c.dtype == "float64"))
    sweep = s.sweep_for(FAKE_METHODS["fake_root"])
    assert set(used) == {"sphere.lead", "torus.a", "csg.a"}  # the lead, then one case per other family
    assert sum(c.case.id == "sphere.lead" and c.dtype == "float64" for c in cfgs) == len(sweep)  # swept on the lead
    f32 = [c for c in cfgs if c.dtype == "float32"]
    assert [(c.case.id, c.knobs) for c in f32] == [("sphere.lead", sweep[0])]  # float32: defaults, first case


def test_reference_rays_are_evenly_strided_and_include_both_ends():
    from bench.run.references import reference_rays

    assert list(reference_rays(10, None)) == list(range(10))
    assert list(reference_rays(10, 32)) == list(range(10))
    idx = reference_rays(4096, 32)
    assert len(idx) == 32 and idx[0] == 0 and idx[-1] == 4095 and np.all(np.diff(idx) > 0)
    assert np.ptp(np.diff(idx)) <= 1  # even spacing


@pytest.mark.parametrize("suite_name", ["quick", "full"])
def test_workload_scenes_run_on_every_applicable_method(suite_name):
    """The suites' ``always_cases``: every mesh, grid and neural case the suite selects runs on
    every root finder, the surface renderer and the gradients where they apply (beyond
    ``max_cases``), at default knobs, except where the suite excludes them by name
    (``exclude_cases``: dt/dθ of the neural SDF's 4481 weights); the volume renderers are not
    planned on them."""
    import fnmatch

    from bench.run.suites import get_suite
    from reference import catalog

    suite = get_suite(suite_name)
    cfgs = runner.plan(suite, ["numpy"], None, None, None)
    planned = {(c.case.id, c.method) for c in cfgs}
    workloads = [c for c in planning.select_cases(suite, None)
                 if any(fnmatch.fnmatchcase(c.id, g) for g in ("mesh.*", "grid.*", "neural.*"))]
    assert workloads, "the suite selects no workload case"
    if suite_name == "quick":
        assert any(c.id.startswith("mesh.") for c in workloads)
        assert any(c.id.startswith("neural.") for c in workloads)
    for spec in METHODS.values():
        for case in workloads:
            excluded = (*suite.exclude_cases.get(spec.family, ()), *suite.exclude_cases.get(spec.name, ()))
            if any(fnmatch.fnmatchcase(case.id, g) for g in excluded):
                assert (case.id, spec.name) not in planned, (case.id, spec.name)
            elif spec.family in ("root", "gradient", "param_grad") or spec.name == "render_surface":
                assert (case.id, spec.name) in planned, (case.id, spec.name)
                if planning.applies(spec, case) is None:
                    knobs = [c.knobs for c in cfgs if c.case.id == case.id and c.method == spec.name]
                    assert knobs == [suite.sweep_for(spec)[0]]  # default knobs only
            elif spec.family == "render":
                assert (case.id, spec.name) not in planned or case.id in suite.lead_cases.get("render", ())
    assert len(catalog("mesh.*")) >= 3


def test_match_all_case_keeps_the_suites_cost_exclusions_and_named_cases_lift_them():
    """``--case '*'`` (the catalog sweep) leaves out what the suite excludes for cost (dt/dθ by
    finite differences or unrolling on the neural SDF's 4481 weights: each runs past --timeout);
    ``--case 'neural.*'`` names those cases and plans them, with the knob sweep."""
    from bench.run.suites import get_suite

    suite = get_suite("full")
    every = runner.plan(suite, ["numpy"], "*", ["dt_finite_diff", "dt_implicit"], None)
    assert not [c for c in every if c.method == "dt_finite_diff" and c.case.id.startswith("neural.")]
    assert [c for c in every if c.method == "dt_implicit" and c.case.id.startswith("neural.")]
    assert [c for c in every if c.method == "dt_finite_diff" and c.case.id.startswith("mlp.")]
    named = runner.plan(suite, ["numpy"], "neural.*", ["dt_finite_diff"], None)
    applicable = [c for c in named if planning.applies(METHODS[c.method], c.case) is None]
    assert applicable and all(c.case.id.startswith("neural.") for c in named)
    assert len({json.dumps(c.knobs, sort_keys=True) for c in applicable}) == len(suite.sweep_for(METHODS["dt_finite_diff"]))


def test_workloads_suite_plans_only_workload_cases_with_every_root_finder():
    """``--suite workloads``: every mesh, grid and neural case of the catalog, no other case, each
    root finder and the surface renderer on each (default knobs, float64), the gradients where the
    scene is smooth."""
    import fnmatch

    from bench.run.suites import get_suite
    from reference import catalog

    suite = get_suite("workloads")
    cfgs = runner.plan(suite, ["numpy"], None, None, None)
    ids = {c.case.id for c in cfgs}
    expected = {c.id for c in catalog() if any(fnmatch.fnmatchcase(c.id, g) for g in ("mesh.*", "grid.*", "neural.*"))}
    assert ids == expected and len(expected) >= 10
    # float64, but for a method that computes in its own dtype (an engine's raycast: float32)
    assert {c.dtype for c in cfgs if METHODS[c.method].dtypes is None} == {"float64"}
    assert {c.dtype for c in cfgs if c.method == "raycast"} == {"float32"}
    planned = {(c.case.id, c.method) for c in cfgs}
    for case in catalog():
        if case.id not in expected:
            continue
        for name in [m for m, s in METHODS.items() if s.family == "root"] + ["render_surface"]:
            assert (case.id, name) in planned, (case.id, name)
    for c in cfgs:
        assert c.knobs == suite.sweep_for(METHODS[c.method])[0]


def test_costly_writes_are_spaced_so_writing_stays_a_small_share_of_the_run(fake_methods, tmp_path, monkeypatch):
    """The results are rewritten whole, so a write's cost grows with the run: the runner waits
    FLUSH_COST_FACTOR × the last write's cost between writes (with flush_s = 0 it would write after
    every configuration), and the final write still holds every row."""
    from bench.run import results

    cost, writes = 0.03, []

    def slow_write(df, out_dir):
        writes.append(time.monotonic())
        time.sleep(cost)
        results.write_results(df, out_dir)

    monkeypatch.setattr(runner, "write_results", slow_write)
    s = suite(["fake_root"], sweeps={"fake_root": [{"tol": 1e-6, "max_steps": m, "behaviour": 0}
                                                   for m in range(2, 62)]})
    t0 = time.monotonic()
    df = runner.run(s, {"fake": FakeBackend()}, tmp_path, policy=FAST, flush_s=0.0)
    wall = time.monotonic() - t0
    n_cfg = len(runner.plan(s, ["fake"], None, None, None))
    assert n_cfg >= 60
    assert len(writes) <= wall / (runner.FLUSH_COST_FACTOR * cost) + 2 < n_cfg / 2, (len(writes), wall)
    gaps = np.diff(writes[:-1])  # the last write is the run's closing one, whenever it comes
    assert (gaps >= runner.FLUSH_COST_FACTOR * cost).all(), gaps
    assert len(read_results(tmp_path)) == len(df) and df.groupby(runner.CONFIG_KEY).ngroups == n_cfg


def test_a_method_with_its_own_dtypes_is_planned_in_them():
    """``MethodSpec.dtypes`` (raycast: float32): planned in those whatever the suite's dtypes; narrowed
    to the ones ``--dtype`` names; with ``--dtype`` naming none of them, planned in the run's (and
    skipped there with the reason, not silently left out)."""
    from bench.run.suites import get_suite

    suite = get_suite("quick")
    assert suite.dtypes == ("float64",)
    cfgs = planning.plan(suite, ["numpy"], "sphere.grazing.1e-6", ["raycast", "hybrid_secant"], None)
    assert {(c.method, c.dtype) for c in cfgs} == {("raycast", "float32"), ("hybrid_secant", "float64")}
    both = planning.plan(suite, ["numpy"], "sphere.grazing.1e-6", ["raycast"], ["float64", "float32"])
    assert {c.dtype for c in both} == {"float32"}
    only64 = planning.plan(suite, ["numpy"], "sphere.grazing.1e-6", ["raycast"], ["float64"])
    assert {c.dtype for c in only64} == {"float64"}
    from impls import registry

    reason = configuration.skip_reason(only64[0], registry.resolve("numpy"))
    assert "does not implement raycast" in reason and "engine" in reason


@pytest.mark.slow  # plans the full suite over the whole catalog, cameras at scale built
def test_full_plans_the_cameras_at_scale_quick_does_not(monkeypatch):
    """Every scene kind's camera at scale runs in ``full`` (1024² analytic, CSG and grid; the mesh at
    256² for the root finders), in float64 at default knobs; ``quick`` and ``workloads`` plan none;
    the neural SDF at scale (minutes of numerical reference) only when ``--case`` names it.  (The
    planner reads each case's first hits; the neural camera's numerical ones, 4 minutes at 256²
    here, are stood in for: what is tested is the plan.)"""
    from bench.run.suites import get_suite
    from reference.cases import Case

    monkeypatch.setattr(Case, "numerical_hits", lambda self: (np.full(self.n_rays, np.inf), np.zeros(self.n_rays)))

    def at_scale(cfgs):
        return {(c.case.id, c.method, c.dtype) for c in cfgs if "256x256" in c.case.id or "1024x1024" in c.case.id}

    full = planning.plan(get_suite("full"), ["numpy"], None, ["hybrid_secant", "sphere_trace", "march_bisect"], None)
    got = at_scale(full)
    for cid in ("torus.camera.1024x1024", "csg.union.camera.1024x1024", "grid.torus64.camera.1024x1024",
                "mesh.torus.camera.256x256"):
        assert {(cid, "hybrid_secant", "float64"), (cid, "sphere_trace", "float64")} <= got, cid
    assert {dt for _, _, dt in got} == {"float64"} and not any(m == "march_bisect" for _, m, _ in got)
    assert not any(cid.startswith("neural.") for cid, _, _ in got)
    defaults = {c.case.id: c.knobs for c in full if c.case.id == "torus.camera.1024x1024"}
    assert defaults["torus.camera.1024x1024"] == METHODS["hybrid_secant"].validate({})
    for name in ("quick", "workloads"):
        assert not at_scale(planning.plan(get_suite(name), ["numpy"], None, None, None)), name
    named = planning.plan(get_suite("full"), ["numpy"], "neural.blob.camera.256x256.Llocal", ["hybrid_secant"], None)
    assert at_scale(named)
