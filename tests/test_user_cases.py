"""A user's own case, added from outside the repository, joins the catalog and runs in `bench run`."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
import pytest

from reference import Case, Sphere, catalog, get_case
from reference import user_cases
from tests.conftest import HANG_GUARD_S

MODULE = textwrap.dedent('''
    import numpy as np
    from reference import Case, CallableField
    from reference import rays

    def blob(x, xp):
        return xp.sqrt(xp.sum(x * x, axis=-1)) - 1.0 + 0.1 * xp.sin(4.0 * x[..., 0])

    def make():
        o, d = rays.pinhole(eye=(0.0, 0.0, 3.0), look_at=(0.0, 0.0, 0.0), fov_deg=40.0, width=8, height=8)
        return [Case(id="{prefix}.blob.camera", scene=CallableField(blob, lipschitz=1.4, name="{mod}.blob"),
                     origins=o, directions=d, t_min=0.0, t_max=6.0)]

    CASES = make()
''')


def _write(tmp_path, mod: str, prefix: str):
    (tmp_path / f"{mod}.py").write_text(MODULE.format(prefix=prefix, mod=mod))
    sys.path.insert(0, str(tmp_path))


def test_a_module_attribute_joins_the_catalog(tmp_path):
    _write(tmp_path, "isobench_user_mod1", "user1")
    try:
        ids = user_cases.load("isobench_user_mod1:CASES")
        assert ids == ["user1.blob.camera"]
        case = get_case("user1.blob.camera")
        assert "user" in case.tags and "numerical" in case.tags
        assert [c.id for c in catalog("user1.*")] == ids
        assert np.isfinite(case.exact_t).sum() > 0  # answers from the certified numerical reference
        with pytest.raises(ValueError, match="reuses case ids"):
            user_cases.load("isobench_user_mod1:make")  # the same ids again
    finally:
        sys.path.remove(str(tmp_path))


@pytest.mark.parametrize("spec, match", [
    ("no_colon", "package.module:attribute"),
    ("no_such_module_xyz:CASES", "cannot import"),
    ("reference.cases:NOPE", "no attribute"),
    ("reference.cases:CONFIG_NOT_THERE", "no attribute"),
])
def test_bad_specs_name_the_argument(spec, match):
    with pytest.raises(ValueError, match=match) as e:
        user_cases.load(spec)
    assert "--cases" in str(e.value)


def test_invalid_cases_are_refused_with_the_reason():
    o = np.array([[0.0, 0.0, 3.0]])
    good = dict(id="user.x.one", scene=Sphere(), origins=o, directions=np.array([[0.0, 0.0, -1.0]]))
    user_cases.validate(Case(**good), "t")
    for change, match in [({"id": "nodots"}, "dotted"), ({"directions": np.array([[0.0, 0.0, -2.0]])}, "unit"),
                          ({"origins": np.array([[np.nan, 0, 0]])}, "non-finite"),
                          ({"origins": np.zeros((2, 3))}, "2 origins but 1"), ({"t_min": 5.0, "t_max": 1.0}, "t_min"),
                          ({"origins": np.zeros((1, 2)), "directions": np.zeros((1, 2))}, r"\(n, 3\)")]:
        with pytest.raises(ValueError, match=match):
            user_cases.validate(Case(**{**good, **change}), "t")
    with pytest.raises(TypeError, match="Case objects"):
        user_cases.validate(object(), "t")
    # no closed-form hits: the numerical truth needs a finite range (a run skipped every row of it)
    from reference import CallableField

    blob = CallableField(lambda x, xp: xp.sqrt(xp.sum(x * x, axis=-1)) - 1.0, lipschitz=1.0, name="tests.blob")
    user_cases.validate(Case(**{**good, "scene": blob, "t_max": 6.0}), "t")
    with pytest.raises(ValueError, match=r"'user.x.one' has no closed-form hits.*t_max=inf"):
        user_cases.validate(Case(**{**good, "scene": blob, "t_max": np.inf}), "t")
    user_cases.validate(Case(**{**good, "t_max": np.inf}), "t")  # closed forms need no finite range
    # (before: t_max="6" passed, float("6") being 6, and every row then failed with "must be real
    # number, not str", naming neither t_max nor the fix)
    for value in ("6", None, True):
        with pytest.raises(TypeError, match=r"'user.x.one' t_max must be a real number"):
            user_cases.validate(Case(**{**good, "t_max": value}), "t")


def test_a_user_field_that_exits_interrupts_or_hangs_costs_only_its_cases_rows(monkeypatch, tmp_path):
    """A user's field runs at planning (its numerical first hits, the truth of its case): one that
    calls sys.exit, raises KeyboardInterrupt by itself or hangs made the whole run end (exit 3
    silently, exit 130) or stay in planning past every limit (the 2026-11-30 probe).  Now each is
    its own case's reason, the hang cut at --reference-timeout, and the healthy case runs."""
    import sys
    import time

    from bench.run import runner
    from bench.run.suites import Suite
    from bench.run.timing import TimingPolicy
    from impls import registry
    from reference import CallableField
    from reference import cases as cases_mod
    from reference.cases import register_cases
    from reference.rays import pinhole

    monkeypatch.setattr(cases_mod, "_FACTORIES", dict(cases_mod._FACTORIES))

    def sphere(x, xp):
        return xp.sqrt(xp.sum(x * x, axis=-1)) - 1.0

    def exits(x, xp):
        sys.exit(3)

    def interrupts(x, xp):
        raise KeyboardInterrupt("planted")

    def hangs(x, xp):
        time.sleep(600)

    fields = {"ok": sphere, "exits": exits, "interrupts": interrupts, "hangs": hangs}
    ids = tuple(f"user.ff.{k}" for k in fields)

    def build():
        o, d = pinhole((0, 0, 3), (0, 0, 0), width=4, height=4)
        return [user_cases.validate(Case(id=f"user.ff.{k}", scene=CallableField(fn, lipschitz=1.0, name=f"ff.{k}"),
                                         origins=o, directions=d, t_min=0.0, t_max=6.0), "t") for k, fn in fields.items()]

    register_cases(ids, build)
    suite = Suite(name="t", case_pattern="user.ff.*", dtypes=("float64",), sweeps={"sphere_trace": [{}]},
                  methods=("sphere_trace",))
    policy = TimingPolicy(min_repeats=1, min_time_s=0.0, min_sample_s=0.0, warmup=0, timeout_s=60.0, accuracy_only=True)
    df = runner.run(suite, {"numpy": registry.resolve("numpy")}, tmp_path, policy=policy, reference_timeout_s=5.0)
    by_case = {r.case_id: r for r in df.itertuples()}
    assert by_case["user.ff.ok"].outcome == "ok"
    assert "SystemExit" in by_case["user.ff.exits"].reason
    assert "KeyboardInterrupt: planted" in by_case["user.ff.interrupts"].reason
    assert "ran past the time limit of 5 s (--reference-timeout)" in by_case["user.ff.hangs"].reason


def test_a_case_is_held_to_the_backends_unit_tolerance():
    """A user's directions are unit to float64's rounding, the tolerance the backends
    (impls.base.check_rays) and the numerical reference apply: at 1e-12, as before, a case 1e-13
    off was accepted and then every configuration of it refused by the backends, and its
    numerical truth by the reference."""
    from impls.registry import resolve
    from reference import CallableField, rays

    o, d = rays.pinhole(eye=(0, 0, 3), look_at=(0, 0, 0), fov_deg=40, width=4, height=4)
    blob = CallableField(lambda x, xp: xp.sqrt(xp.sum(x * x, axis=-1)) - 1.0, lipschitz=1.0, name="tests.blob")
    for scene in (Sphere(), blob):
        case = user_cases.validate(Case(id="user.x.unit", scene=scene, origins=o, directions=d, t_max=6.0), "t")
        assert np.isfinite(case.exact_t).sum() > 4
        resolve("numpy").prepare("sphere_trace", case.scene, case.origins, case.directions, t_max=6.0)
        for off in (1e-13, 1e-7):
            with pytest.raises(ValueError, match=r"'user.x.off' directions must be unit .*3\.1e-15.*np.linalg.norm"):
                user_cases.validate(Case(id="user.x.off", scene=scene, origins=o, directions=d * (1 + off)), "t")


@pytest.mark.slow  # three bench commands in fresh interpreters
def test_a_user_case_runs_in_bench_run_from_outside_the_repository(tmp_path):
    """The documented way in: ``--cases module:attr`` with the module on the PYTHONPATH."""
    import os

    import pandas as pd

    mod_dir = tmp_path / "elsewhere"
    mod_dir.mkdir()
    (mod_dir / "isobench_user_mod2.py").write_text(MODULE.format(prefix="user2", mod="isobench_user_mod2"))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(mod_dir), os.environ.get("PYTHONPATH", "")])}
    listed = subprocess.run([sys.executable, "-m", "bench", "cases", "--cases", "isobench_user_mod2:CASES",
                             "--case", "user2.*"], capture_output=True, text=True, env=env, timeout=HANG_GUARD_S)
    assert listed.returncode == 0, listed.stderr
    assert "user2.blob.camera" in listed.stdout and "user" in listed.stdout
    out = tmp_path / "run"
    done = subprocess.run([sys.executable, "-m", "bench", "run", "--cases", "isobench_user_mod2:CASES",
                           "--case", "user2.*", "--backend", "numpy", "--method", "sphere_trace,hybrid_secant",
                           "--accuracy-only", "--no-claims", "--no-progress", "--out", str(out)],
                          capture_output=True, text=True, env=env, timeout=HANG_GUARD_S)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    df = pd.read_csv(out / "results.csv")
    rows = df[(df["case_id"] == "user2.blob.camera") & (df["quantity"] == "depth")]
    assert set(rows["method"]) == {"sphere_trace", "hybrid_secant"}
    assert set(rows["outcome"]) == {"ok"}
    assert (rows["n_false_hit"] == 0).all() and (rows["n_false_miss"] == 0).all()
    bad = subprocess.run([sys.executable, "-m", "bench", "run", "--cases", "nosuchmodule_xyz:CASES", "--no-progress"],
                         capture_output=True, text=True, env=env, timeout=HANG_GUARD_S)
    assert bad.returncode == 2 and "--cases" in bad.stderr and "Traceback" not in bad.stderr


def test_register_cases_builds_once_and_checks_the_ids(monkeypatch):
    """The one registration function: ids registered without building; the builder runs once, on
    the first request, and must build exactly the ids it registered."""
    from reference import Sphere
    from reference import cases as cases_mod
    from reference.cases import case_ids, get_case, make_case, register_cases
    from reference.rays import pinhole

    # a private copy of the catalog: the cases registered here leave no trace for other tests
    monkeypatch.setattr(cases_mod, "_FACTORIES", dict(cases_mod._FACTORIES))

    calls = []

    def build():
        calls.append(1)
        return [make_case(f"test.rc.{k}", Sphere(), *pinhole((0, 0, 3), (0, 0, 0), width=2, height=2),
                          tags=("mine",)) for k in ("a", "b")]

    register_cases(("test.rc.a", "test.rc.b"), build)
    assert {"test.rc.a", "test.rc.b"} <= set(case_ids()) and not calls
    a, b = get_case("test.rc.a"), get_case("test.rc.b")
    assert len(calls) == 1 and a.tags[:1] == ("sphere",) and "mine" in b.tags
    assert a.origins.dtype == np.float64 and a.origins.flags.c_contiguous
    with pytest.raises(ValueError, match="duplicate case id 'test.rc.a'"):
        register_cases(("test.rc.a",), build)
    register_cases(("test.rc.c",), build)  # builds a and b, not c
    with pytest.raises(AssertionError, match="registered as"):
        get_case("test.rc.c")


def test_declared_tags_select_without_building_and_are_checked(monkeypatch):
    """Tags declared at registration: the catalog selects by them without building the case (a
    case of the wrong tag, or one at scale, is never built), and a built case whose tags differ
    from its declaration is an error naming the case."""
    from reference import Sphere
    from reference import cases as cases_mod
    from reference.cases import case_tags, catalog, get_case, make_case, register_cases
    from reference.rays import pinhole

    monkeypatch.setattr(cases_mod, "_FACTORIES", dict(cases_mod._FACTORIES))
    monkeypatch.setattr(cases_mod, "_DECLARED_TAGS", dict(cases_mod._DECLARED_TAGS))
    get_case.cache_clear()
    built = []

    def factory(cid, tags):
        def build():
            built.append(cid)
            return [make_case(cid, Sphere(), *pinhole((0, 0, 3), (0, 0, 0), width=2, height=2), tags=tags)]
        return build

    ok, scale, liar = (("mine", "camera"), ("mine", "camera", "large"), ("mine",))
    register_cases(("test.dt.ok",), factory("test.dt.ok", ok), {"test.dt.ok": case_tags(Sphere(), ok)})
    register_cases(("test.dt.big",), factory("test.dt.big", scale), {"test.dt.big": case_tags(Sphere(), scale)})
    # declared "camera", built without it
    register_cases(("test.dt.liar",), factory("test.dt.liar", liar), {"test.dt.liar": case_tags(Sphere(), ok)})
    with pytest.raises(ValueError, match="not registered here"):
        register_cases(("test.dt.x",), factory("test.dt.x", ok), {"test.dt.y": ok})

    assert [c.id for c in catalog("test.dt.*", {"nosuchtag"})] == [] and built == []
    assert [c.id for c in catalog("test.dt.[bo]*")] == ["test.dt.ok"] and built == ["test.dt.ok"]
    assert [c.id for c in catalog("test.dt.big", {"large"})] == ["test.dt.big"]
    with pytest.raises(AssertionError, match=r"'test.dt.liar' with tags .* declared as"):
        catalog("test.dt.liar", {"camera"})
    # tags_of reads a declaration without building (the report's stability matrix asks it of
    # every case of its rows, a mesh case among them)
    register_cases(("test.dt.late",), factory("test.dt.late", ok), {"test.dt.late": case_tags(Sphere(), ok)})
    assert set(cases_mod.tags_of("test.dt.late")) == set(case_tags(Sphere(), ok)) and "test.dt.late" not in built
    with pytest.raises(KeyError, match="unknown case"):
        cases_mod.tags_of("test.dt.nosuch")
    get_case.cache_clear()


@pytest.mark.parametrize("full", [False, pytest.param(True, marks=pytest.mark.slow)], ids=["to-256", "1024"])
def test_every_declared_tag_set_is_the_built_cases(full):
    """The built-in cases that declare their tags (meshes, grids, the neural SDF, the cameras at
    scale) are built with exactly those tags: building each one checks it.  The 1024² cameras
    (1M rays each, kept by the catalog once built) in the slow tier."""
    from reference import cases as cases_mod
    from reference.cases import FULL_ONLY, get_case

    declared = {cid: tags for cid, tags in cases_mod._DECLARED_TAGS.items() if (FULL_ONLY in tags) == full}
    assert len(declared) >= (4 if full else 20)
    for cid, tags in declared.items():
        assert set(get_case(cid).tags) == tags, cid


def _import_fresh(folder, name: str, source: str):
    """Module ``name`` with ``source``, written to ``folder`` and imported afresh (a user's edit)."""
    import importlib

    folder.mkdir(exist_ok=True)
    (folder / f"{name}.py").write_text(source)
    sys.modules.pop(name, None)
    sys.path.insert(0, str(folder))
    try:
        return importlib.import_module(name)
    finally:
        sys.path.remove(str(folder))
        sys.modules.pop(name, None)


def test_an_edited_user_field_is_another_scene_to_the_kept_references(tmp_path):
    """A ``CallableField``'s content hash holds what its function computes, not only its ``name``:
    a user who edits the function and keeps the name (and the case id) gets the new field's
    reference answers, not the old ones kept on disk (before, the numerical first hits were read
    back from the cache directory for the old body: every correct answer then judged wrong), and
    the same function hashes alike in another process (the kept answers are reused)."""
    from bench.run.references import load_numerical_hits
    from reference import CallableField, rays

    src = textwrap.dedent('''
        R = {r}

        def ball(x, xp):
            return xp.sqrt(xp.sum(x * x, axis=-1)) - R
    ''')
    o, d = rays.pinhole(eye=(0.0, 0.0, 3.0), look_at=(0.0, 0.0, 0.0), fov_deg=30.0, width=4, height=4)
    disk = tmp_path / "kept"
    disk.mkdir()
    hits, hashes = {}, {}
    for r in (0.5, 0.6, 0.5):
        user_ball = _import_fresh(tmp_path / f"edited_{str(r).replace('.', '_')}", "user_ball", src.format(r=r))
        scene = CallableField(user_ball.ball, lipschitz=1.0, name="user_ball.ball")
        case = Case(id="user.edited.ball", scene=scene, origins=o, directions=d, t_min=0.0, t_max=6.0)
        load_numerical_hits(case, disk)
        hits[r], hashes[r] = np.asarray(case.exact_t), scene.content_hash()
        np.testing.assert_allclose(hits[r], Sphere(radius=r).first_hit(o, d, 0.0), atol=1e-9)
    assert hashes[0.5] != hashes[0.6]
    out = subprocess.run([sys.executable, "-c", "import sys; sys.path.insert(0, sys.argv[1]); import user_ball; "
                          "from reference import CallableField; "
                          "print(CallableField(user_ball.ball, lipschitz=1.0, name='user_ball.ball').content_hash())",
                          str(tmp_path / "edited_0_5")], capture_output=True, text=True, timeout=HANG_GUARD_S, check=True)
    assert out.stdout.strip() == hashes[0.5]


def test_a_helper_in_another_module_and_a_bound_methods_instance_are_in_the_hash(tmp_path):
    """A field that calls a helper of another module of the user's, or is a bound method whose
    instance holds its parameter, hashes what those compute: an edit of the helper's file (radius
    1.0 → 1.3) kept the case version, so the kept reference answers of the old field judged the new
    one (64 false hits on a correct numpy hybrid_secant, probe of 2026-11-30) and ``--resume``
    mixed rows of two surfaces under one version; ``Ball(0.3).phi`` and ``Ball(1.3).phi`` had one
    version too."""
    from reference import CallableField

    field = textwrap.dedent('''
        import {helper}

        def ball(x, xp):
            return xp.sqrt(xp.sum(x * x, axis=-1)) - {helper}.radius()
    ''')
    got = []
    for i, r in enumerate((1.0, 1.3, 1.0)):
        folder = tmp_path / f"h{i}"
        folder.mkdir()
        (folder / "user_radius.py").write_text(f"def radius():\n    return {r}\n")
        sys.path.insert(0, str(folder))
        try:
            sys.modules.pop("user_radius", None)
            user_field = _import_fresh(folder, "user_field", field.format(helper="user_radius"))
            got.append(CallableField(user_field.ball, lipschitz=1.0, name="user_field.ball").content_hash())
        finally:
            sys.path.remove(str(folder))
            sys.modules.pop("user_radius", None)
    assert got[0] == got[2] != got[1]

    balls = _import_fresh(tmp_path / "b", "user_balls", textwrap.dedent('''
        class Ball:
            def __init__(self, r):
                self.r = r

            def phi(self, x, xp):
                return xp.sqrt(xp.sum(x * x, axis=-1)) - self.r
    '''))
    hashes = [CallableField(balls.Ball(r).phi, lipschitz=1.0, name="ball").content_hash() for r in (0.3, 1.3, 0.3)]
    assert hashes[0] == hashes[2] != hashes[1]
    # numpy's functions read through a module global are the library's, not hashed member by member
    np_field = _import_fresh(tmp_path / "n", "user_np", "import numpy as np\n\ndef f(x, xp):\n    return np.sqrt(3.0) + x[..., 0]\n")
    assert CallableField(np_field.f, lipschitz=1.0, name="f").content_hash()


def test_an_edited_user_field_class_is_another_scene(tmp_path):
    """The same for a user's own ``Field`` subclass: its content hash holds its class's code (the
    file that defines it), which the package's source digests do not cover; the library's nodes
    keep theirs (the committed baseline's case versions)."""
    src = textwrap.dedent('''
        from reference.scene import Field, SceneInfo

        class Slab(Field):
            kind = "slab"

            @property
            def info(self):
                return SceneInfo(exact_sdf=True, lipschitz=1.0, distance_bound=True, smooth=True, exact_hits=False,
                                 exact_normals=False, exact_curvature=False, exact_hit_param_grad=False)

            def _eval(self, x, xp, cursor):
                return xp.abs(x[..., 2]) - {w}
    ''')
    got = []
    for i, w in enumerate((0.1, 0.2, 0.1)):
        got.append(_import_fresh(tmp_path / f"v{i}", "user_slab", src.format(w=w)).Slab().content_hash())
    assert got[0] == got[2] != got[1]
    import pandas as pd
    from pathlib import Path

    base = pd.read_csv(Path(__file__).resolve().parents[1] / "reports" / "baseline" / "results.csv",
                       usecols=["case_id", "case_version"], dtype=str).drop_duplicates()
    for cid, version in base.itertuples(index=False):
        assert get_case(cid).version == version, cid


class _WrongHitsSphere(Sphere):
    """A user's unit-sphere field whose closed-form ``first_hit`` is wrong as ``mode`` says (a
    user's Field subclass: its hits are a claim, checked against the numerical reference)."""

    def __init__(self, mode: str):
        super().__init__()
        self.mode = mode

    def _static_spec(self):
        return {**super()._static_spec(), "mode": self.mode}

    def first_hit(self, o, d, t_min=0.0):
        t = np.asarray(super().first_hit(o, d, t_min), np.float64)
        if self.mode == "exit":  # the second crossing: the entry mirrored through the chord's midpoint
            b = np.einsum("ij,ij->i", o, d)
            return np.where(np.isfinite(t), -2.0 * b - t, np.inf)
        if self.mode == "halfmiss":
            t = t.copy()
            t[np.flatnonzero(np.isfinite(t))[::2]] = np.inf
            return t
        if self.mode == "nan":
            return np.where(np.arange(t.size) % 3 == 0, np.nan, t)
        return t[:, None] if self.mode == "shape" else t


@pytest.mark.parametrize("mode, words", [("exit", "disagrees with the numerical reference's first crossing"),
                                         ("halfmiss", "disagrees with the numerical reference's first crossing"),
                                         ("nan", "first_hit returned NaN on"),
                                         ("shape", "first_hit returned shape (64, 1), expected (64,)")])
def test_a_users_closed_form_first_hit_is_checked(mode, words):
    """Before (the 2026-12-01 user-field probe): a user's ``first_hit`` was taken as the truth: the
    exit instead of the entry charged a correct backend 2.0 of depth error, inf on every other hit
    1,512 false hits, a NaN was a judged MISS, an (n, 1) array a numpy broadcast error."""
    from reference.cases import make_case
    from reference.rays import pinhole
    from reference.scene import FieldError

    o, d = pinhole((0, 0, 3), (0, 0, 0), width=8, height=8, fov_deg=50)
    case = make_case(f"test.wrong.{mode}", _WrongHitsSphere(mode), o, d, t_max=6.0)
    with pytest.raises(FieldError, match=words.replace("(", r"\(").replace(")", r"\)")):
        case.exact_t
    good = make_case("test.wrong.none", _WrongHitsSphere("none"), o, d, t_max=6.0)
    assert np.isfinite(good.exact_t).sum() > 0
