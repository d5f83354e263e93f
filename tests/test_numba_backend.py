"""The numba backend (``impls/numba``), a plug-in: registration by entry point, agreement with
numpy's array drivers (the same algorithms, so the same statuses, counts and depths: to the bit
where numpy's φ does not call BLAS, to rounding where it does), statuses on flagged rays, the
Lipschitz check, declined scenes (skipped rows in a run) and compile-once caching.

The conformance suite runs it too: ``ISOBENCH_EXTRA_BACKENDS=impls.numba.backend:NumbaBackend
python -m pytest tests/conformance/``."""

from __future__ import annotations

import importlib.util
import sys
import warnings

import numpy as np
import pytest

from impls import METHODS, Declined, Status, registry
from reference import Box, Sphere, Torus, Transform, Union, get_case
from reference.rays import pinhole

#: numba compiles kernels for nearly every test here (the slow tier; CI runs it)
pytestmark = pytest.mark.slow

HAVE_NUMBA = importlib.util.find_spec("numba") is not None
needs_numba = pytest.mark.skipif(not HAVE_NUMBA, reason="numba is not installed (pip install -e '.[numba]')")

#: the root methods every backend offers (``MethodSpec.libs`` None; scipy's refiners are numpy's)
ROOTS = [m for m, s in METHODS.items() if s.family == "root" and s.libs is None]


def _fake_entry_point(tmp_path, monkeypatch):
    """The entry point pyproject.toml declares, as ``pip install -e .`` would publish it, in a fake
    dist-info on sys.path (installing would repoint the shared environment)."""
    dist = tmp_path / "isobench_numba_probe-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: isobench-numba-probe\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text(f"[{registry.ENTRY_POINT_GROUP}]\nnumba = impls.numba.backend:NumbaBackend\n")
    monkeypatch.syspath_prepend(str(tmp_path))


def test_pyproject_declares_the_entry_point_and_the_extra():
    import tomllib
    from pathlib import Path

    meta = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())["project"]
    assert meta["entry-points"][registry.ENTRY_POINT_GROUP]["numba"] == "impls.numba.backend:NumbaBackend"
    # filelock: the on-disk kernel cache's lock (impls.cache.lock_numba_cache)
    assert meta["optional-dependencies"]["numba"] == ["numba>=0.60", "filelock>=3.12"]
    assert any("numba" in extra for extra in meta["optional-dependencies"]["all"])  # CI installs [all]
    pins = (Path(__file__).parents[1] / "constraints.txt").read_text().split()
    assert "numba==0.68.1" in pins and "llvmlite==0.50.0" in pins and "filelock==4.3.1" in pins


@needs_numba
def test_plugs_in_by_entry_point(tmp_path, monkeypatch):
    """The entry point makes it a default backend, resolved by id ``numba``."""
    from impls.numba.backend import NumbaBackend

    _fake_entry_point(tmp_path, monkeypatch)
    assert "numba" in registry.default_ids()
    b = registry.resolve("numba")
    assert isinstance(b, NumbaBackend) and b.id == "numba"
    assert set(b.methods()) == set(ROOTS) | {"render_surface"}


def test_without_numba_it_is_unavailable_with_the_install_command(tmp_path, monkeypatch):
    """Without numba the entry point resolves to Unavailable whose reason is the install command,
    and a run records its configurations as skipped with it."""
    from bench.run.configuration import Config, skip_reason

    _fake_entry_point(tmp_path, monkeypatch)
    monkeypatch.setitem(sys.modules, "numba", None)  # numba not installed
    monkeypatch.delitem(sys.modules, "impls.numba.backend", raising=False)
    gone = registry.resolve("numba")
    assert isinstance(gone, registry.Unavailable) and not gone.unknown
    assert ".[numba]" in gone.reason and "pip install" in gone.reason
    case = get_case("sphere.camera.64x64")
    reason = skip_reason(Config(case, "numba", "hybrid_secant", "float64", {}), gone)
    assert reason.startswith("backend unavailable") and ".[numba]" in reason


# -- agreement with numpy -----------------------------------------------------------------------


@pytest.fixture(scope="module")
def nb():
    if not HAVE_NUMBA:
        pytest.skip("numba is not installed (pip install -e '.[numba]')")
    from impls.numba.backend import NumbaBackend

    return NumbaBackend()


def run(backend, method, scene, o, d, **kw):
    p = backend.prepare(method, scene, o, d, **kw)
    return p.result(p.run())


def _scene(name):
    if name == "sphere":
        return (Sphere(center=(0.1, -0.2, 0.05), radius=0.8),) + pinhole(eye=(0.3, 0.2, 3.0), look_at=(0, 0, 0),
                                                                          fov_deg=45, width=24, height=24)
    if name == "torus∪box":
        return (Union(Torus(1.0, 0.25), Box((0.4, 0.4, 0.4))),) + pinhole(eye=(0.5, -2.5, 1.5), look_at=(0, 0, 0),
                                                                          fov_deg=50, width=24, height=24)
    if name == "transformed":  # a rotated, translated torus: φ(x) = φ_torus((x − τ) R)
        return (Transform.from_rotvec(Torus(1.0, 0.3), (0.4, -0.3, 0.8), (0.2, -0.1, 0.3)),) + pinhole(
            eye=(0.3, -2.8, 1.2), look_at=(0.2, -0.1, 0.3), fov_deg=55, width=24, height=24)
    case = get_case("mlp.camera.32x32")
    return case.scene, case.origins, case.directions


#: where numpy's φ calls BLAS (matmul: the transform's rotation, the MLP's layers) the two sum in
#: different orders: depths agree to rounding, counts may differ where a convergence test is that close
#: (measured over the catalog's compiled cases: statuses equal everywhere, depths within 4e-14)
BLAS = {"transformed", "mlp"}


@pytest.mark.parametrize("method,ladder", [("sphere_trace", None)] + [(m, k) for m in ROOTS if m != "sphere_trace"
                                                                       for k in (0, 16)])
@pytest.mark.parametrize("name", ["sphere", "torus∪box", "transformed", "mlp"])
def test_root_finders_agree_with_numpy(nb, name, method, ladder):
    """Same algorithm, same knobs: the same status, iterations and evaluations on every ray, and the
    same depth — bit for bit on the sphere and the CSG, within 1e-12 where numpy's φ uses BLAS.
    (ladder 0: the marchers run in the lanes kernel, Newton's too; 16: one ray at a time.)"""
    scene, o, d = _scene(name)
    # (sphere tracing on the MLP, whose L is loose, needs more than the default 512 steps)
    kw = dict(t_max=10.0, max_steps=20000) if method == "sphere_trace" else dict(t_max=10.0, ladder=ladder)
    a, b = run(nb, method, scene, o, d, **kw), run(registry.resolve("numpy"), method, scene, o, d, **kw)
    np.testing.assert_array_equal(a.status, b.status)
    # hits answered (a hybrid's ladder spaces its samples by the forced step near the MLP's surface, whose
    # pairs stand uncertified: those hits are UNCERTIFIED, with their depth, on both backends)
    answered = np.isin(a.status, (Status.CONVERGED, Status.UNCERTIFIED))
    assert answered.sum() >= 40 and (a.status == Status.MISS).any(), a.status_counts()
    if name in BLAS:
        np.testing.assert_allclose(a.t, b.t, rtol=0, atol=1e-12)
        # a convergence test that close can fall a step or more apart (Newton's φ' is a central
        # difference, which turns the last-bit difference of φ into ~1e-11 relative)
        same = np.mean(a.iterations == b.iterations)
        assert same >= 0.85 and abs(int(a.iterations.sum()) - int(b.iterations.sum())) <= 0.02 * b.iterations.sum(), same
    else:
        np.testing.assert_array_equal(a.t, b.t)
        np.testing.assert_array_equal(a.iterations, b.iterations)
        np.testing.assert_array_equal(a.evals, b.evals)


@pytest.mark.parametrize("method", ["march_secant", "march_bisect"])
def test_a_union_of_many_children_agrees_with_numpy(nb, method):
    """From ``csg.MANY_BOUNDS`` children on a union is bounded by its children's balls
    (:meth:`reference.csg.Union.ray_bounds`); the marchers' generated bounds do the same (the
    certified methods run numpy's driver, which takes the scene's own), so the two backends march
    the same intervals: statuses, depths, evaluations equal."""
    from reference import Box
    from reference.csg import MANY_BOUNDS

    rng = np.random.default_rng(3)
    kids = [Sphere(center=tuple(rng.uniform(-1, 1, 3)), radius=0.2) if i % 2 else
            Transform(Box((0.15, 0.1, 0.2)), translation=tuple(rng.uniform(-1, 1, 3))) for i in range(MANY_BOUNDS + 2)]
    o, d = pinhole(eye=(0.4, -0.3, 3.5), look_at=(0, 0, 0), fov_deg=50, width=24, height=24)
    kw = dict(t_max=10.0, ladder=0)  # the lanes kernel, with the generated bounds
    a, b = run(nb, method, Union(*kids), o, d, **kw), run(registry.resolve("numpy"), method, Union(*kids), o, d, **kw)
    assert (a.status == Status.MISS).any() and (a.status == Status.CONVERGED).sum() >= 40, a.status_counts()
    np.testing.assert_array_equal(a.status, b.status)
    np.testing.assert_array_equal(a.t, b.t)
    np.testing.assert_array_equal(a.evals, b.evals)


def test_render_surface_agrees_with_numpy(nb):
    scene, o, d = _scene("torus∪box")
    a, b = run(nb, "render_surface", scene, o, d, ladder=16), run(registry.resolve("numpy"), "render_surface",
                                                                  scene, o, d, ladder=16)
    np.testing.assert_array_equal(a.status, b.status)
    np.testing.assert_array_equal(a.outputs["color"], b.outputs["color"])


def _odd_rays():
    """Rays at the unit sphere from x = −3: impact parameters 1 − 1e-3 (grazing hit), 1 + 1e-3
    (grazing miss), 0.5, 2 (wide miss); then a NaN origin, an inf origin, a zero and a NaN direction."""
    b = np.array([1 - 1e-3, 1 + 1e-3, 0.5, 2.0, 0.0, 0.0, 0.0, 0.0])
    o = np.stack([np.full(8, -3.0), b, np.zeros(8)], axis=1)
    d = np.tile([1.0, 0.0, 0.0], (8, 1))
    o[4, 0], o[5, 2] = np.nan, np.inf
    d[6], d[7, 1] = 0.0, np.nan
    return o, d


@pytest.mark.parametrize("method", ROOTS)
def test_statuses_of_grazing_missing_and_bad_rays(nb, method):
    o, d = _odd_rays()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        ref = run(registry.resolve("numpy"), method, Sphere(), o, d, t_max=10.0)
    r = run(nb, method, Sphere(), o, d, t_max=10.0)
    np.testing.assert_array_equal(r.status, ref.status)
    assert np.all(r.status[4:] == Status.BAD_INPUT) and np.all(np.isnan(r.t[4:]))
    assert np.all(r.evals[4:] == 0) and np.all(r.iterations[4:] == 0)
    assert r.status[3] == Status.MISS and np.isinf(r.t[3]) and r.evals[3] == 0  # outside the ray bounds
    assert r.status[2] == Status.CONVERGED and abs(r.t[2] - (3 - np.sqrt(0.75))) <= 1e-9
    assert r.status[1] == Status.MISS
    if method != "sphere_trace":  # tol 1e-10 on |φ| ends far from the grazing root
        assert r.status[0] == Status.CONVERGED and abs(r.t[0] - (3 - np.sqrt(1 - (1 - 1e-3) ** 2))) <= 1e-9
    # a step budget too small: MAX_ITER with the last iterate
    r = run(nb, "sphere_trace", Sphere(), o[:1], d[:1], t_max=10.0, max_steps=3)
    assert r.status[0] == Status.MAX_ITER and np.isfinite(r.t[0]) and r.iterations[0] == 3


@pytest.mark.filterwarnings("ignore:overflow:RuntimeWarning")  # the scene's extent, on purpose
def test_non_finite_phi_is_non_finite(nb):
    """A sphere centred at 1e300: |x − c|² overflows, φ = inf at the start (no ray bounds)."""
    o, d = _odd_rays()
    r = run(nb, "sphere_trace", Sphere(center=(1e300, 0.0, 0.0)), o[:3], d[:3], t_max=10.0, bounds=0)
    assert np.all(r.status == Status.NON_FINITE) and np.all(np.isnan(r.t)) and np.all(r.evals == 1)


@pytest.mark.parametrize("method", ["sphere_trace", "hybrid_secant", "march_secant"])
def test_understated_lipschitz_bound_is_flagged(nb, method):
    """10 × a hollow ball declared with L = 1 (true L = 10): a step φ/L would jump the shell, and
    the step's slope shows the bound is false — LIPSCHITZ_VIOLATED with t = NaN, as numpy."""
    case = get_case("shell.understated.L10")
    kw = dict(t_min=case.t_min, t_max=case.t_max)
    r = run(nb, method, case.scene, case.origins, case.directions, **kw)
    ref = run(registry.resolve("numpy"), method, case.scene, case.origins, case.directions, **kw)
    np.testing.assert_array_equal(r.status, ref.status)
    flagged = r.status == Status.LIPSCHITZ_VIOLATED
    assert flagged.mean() > 0.5 and np.all(np.isnan(r.t[flagged])), r.status_counts()
    # no false answer: every CONVERGED depth is the true hit (the inner sphere |x| = 0.9)
    ok = r.status == Status.CONVERGED
    np.testing.assert_allclose(r.t[ok], case.exact_t[ok], rtol=0, atol=1e-8)


def test_declines_a_mesh_scene_and_a_run_skips_it(nb):
    from bench.run.configuration import Config, run_one
    from bench.run.timing import TimingPolicy

    case = get_case("mesh.torus.camera.16x16")
    reason = nb.declines("hybrid_secant", case.scene)
    assert reason and "MeshSDF" in reason
    with pytest.raises(Declined, match="MeshSDF"):
        nb.prepare("hybrid_secant", case.scene, case.origins, case.directions)
    rows = run_one("t", Config(case, "numba", "hybrid_secant", "float64", {}), nb, TimingPolicy(), 1.0)
    assert len(rows) == 1 and rows[0]["outcome"] == "skipped", rows
    assert "declines" in rows[0]["reason"] and "MeshSDF" in rows[0]["reason"]


def test_a_declined_prepare_is_a_skipped_row_not_a_failure(nb):
    """A backend without the ``declines`` hook that raises Declined from ``prepare``: skipped."""
    from bench.run.configuration import Config, run_one
    from bench.run.timing import TimingPolicy

    class Refusing:
        id, lib, device, capabilities = "refusing", "refusing", "cpu", nb.capabilities

        def methods(self):
            return nb.methods()

        def prepare(self, *a, **k):
            raise Declined("not today")

        def synchronize(self, out=None):
            pass

    case = get_case("sphere.camera.64x64")
    rows = run_one("t", Config(case, "refusing", "hybrid_secant", "float64", {}), Refusing(), TimingPolicy(), 1.0)
    assert [r["outcome"] for r in rows] == ["skipped"] and "not today" in rows[0]["reason"]


def test_float32_is_not_offered(nb):
    scene, o, d = _scene("sphere")
    with pytest.raises(ValueError, match="float32"):
        nb.prepare("hybrid_secant", scene, o, d, dtype="float32")


def test_compiles_once_per_scene_structure(nb):
    """The kernels are cached by the scene's structure (its generated source): the same scene, or one
    of the same structure with other numbers, reuses them (``compile_cache``) and gives its own answers."""
    from impls.numba import driver, fields

    o, d = pinhole(eye=(0, 0, 3.0), look_at=(0, 0, 0), fov_deg=40, width=8, height=8)
    a = Union(Sphere(center=(0.3, 0, 0), radius=0.5), Box((0.2, 0.3, 0.4)))
    b = Union(Sphere(center=(-0.2, 0.1, 0), radius=0.7), Box((0.5, 0.1, 0.2)))
    ka, kb = fields.compile_scene(a), fields.compile_scene(b)
    assert ka.key == kb.key and not np.array_equal(ka.params, kb.params)
    assert fields.compile_scene(Union(Box((0.2, 0.3, 0.4)), Sphere())).key != ka.key  # another structure
    first = nb.prepare("hybrid_secant", a, o, d, t_max=10.0)
    assert driver.kernels(ka.key) is driver.kernels(kb.key)
    again = nb.prepare("hybrid_secant", b, o, d, t_max=10.0)
    # the first may have come from the disk cache of an earlier session: "compiled" or "reused"
    assert first.compile_cache in ("compiled", "reused") and again.compile_cache == "reused"
    for scene, prep in ((a, first), (b, again)):
        r = prep.result(prep.run())
        ref = run(registry.resolve("numpy"), "hybrid_secant", scene, o, d, t_max=10.0, ladder=0)
        np.testing.assert_array_equal(r.t, ref.t)


def test_threads_are_a_setting_and_do_not_change_results(nb):
    import numba

    from bench.run.environment import configure_driver, driver_record

    scene, o, d = _scene("torus∪box")
    one = run(nb, "hybrid_secant", scene, o, d, t_max=10.0)
    b2 = type(nb)()
    configure_driver(b2, min(2, numba.config.NUMBA_NUM_THREADS))
    assert '"threads": %d' % b2.settings.threads in driver_record(b2) and '"driver": "per-ray"' in driver_record(b2)
    two = run(b2, "hybrid_secant", scene, o, d, t_max=10.0)
    np.testing.assert_array_equal(one.t, two.t)
    np.testing.assert_array_equal(one.evals, two.evals)
    with pytest.raises(ValueError, match="NUMBA_NUM_THREADS"):
        b2.configure(threads=numba.config.NUMBA_NUM_THREADS + 1)


def test_one_thread_runs_serial_kernels_with_the_parallel_kernels_results(nb):
    """One thread runs kernels compiled without numba's parallel loops, more threads the ``prange``
    ones (:func:`impls.numba.driver.kernels`): the same rays, bit for bit, in each kernel (the
    lanes kernel, Newton's derivative in it, φ along rays for sphere tracing)."""
    import numba

    from impls.numba import driver, fields

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("numba has one thread (NUMBA_NUM_THREADS): no parallel kernels to compare")
    scene, o, d = _scene("torus∪box")
    b2 = type(nb)()
    b2.configure(threads=2)
    assert nb.settings.threads == 1
    key = fields.compile_scene(scene).key
    assert driver.kernels(key, False) is not driver.kernels(key, True)
    for method in ("march_bisect", "march_newton", "sphere_trace"):
        a, b = run(nb, method, scene, o, d, t_max=10.0), run(b2, method, scene, o, d, t_max=10.0)
        assert (a.status == Status.CONVERGED).sum() > 40
        for k in ("t", "status", "iterations", "evals"):
            np.testing.assert_array_equal(getattr(a, k), getattr(b, k), err_msg=f"{method} {k}")


def test_knobs_come_from_the_catalog(nb):
    """Defaults are the catalog's (nothing re-defaulted): passing every default explicitly changes
    nothing, and a bad knob is refused with its name."""
    scene, o, d = _scene("sphere")
    defaults = {k.name: k.default for k in METHODS["hybrid_secant"].knobs}
    np.testing.assert_array_equal(run(nb, "hybrid_secant", scene, o, d).t,
                                  run(nb, "hybrid_secant", scene, o, d, **defaults).t)
    with pytest.raises(ValueError, match="xtol"):
        nb.prepare("hybrid_secant", scene, o, d, xtol=-1.0)
    r = run(nb, "march_newton", scene, o, d, step=0.05)  # dφ/dt by central differences: 3 evaluations each
    assert np.all(r.evals[r.status == Status.CONVERGED] % 3 == 0)


# -- the kernels: one template per step, the refiners they compile -------------------------------


def _march(method="march_secant", **knobs):
    scene, _, _ = _scene("sphere")
    spec = METHODS[method]
    return spec.algorithm(scene, 0.0, 10.0, spec.validate(knobs), ladder=0)


def test_the_refiners_are_mapped_explicitly_and_an_unknown_one_is_an_error():
    """The kernels compile Bisect, Secant and Newton (0, 1, 2 in the configuration).  Any other
    refiner — a user's subclass with its own proposal, or march_chandrupatla's scipy refinement
    (a MarchRefine subclass whose refiner field is a placeholder Bisect) — is refused naming it and
    what is compiled, instead of being run as another refiner's steps."""
    import dataclasses

    from impls.core.rootfind import Bisect, Newton, Secant
    from impls.numba import driver

    alg = _march()
    for ref, k in ((Bisect(), 0), (Secant(), 1), (Newton(), 2)):
        assert driver.configuration(dataclasses.replace(alg, refiner=ref))[2][driver.I_REFINER] == k

    class DampedSecant(Secant):  # a user's refiner: another proposal
        def _iterate(self, xp, s, t, f):
            return t - 0.5 * f * (t - s["p"]) / (f - s["fp"])

    with pytest.raises(NotImplementedError, match="DampedSecant is not one of them") as err:
        driver.configuration(dataclasses.replace(alg, refiner=DampedSecant()))
    assert "Bisect, Secant, Newton" in str(err.value)
    with pytest.raises(NotImplementedError, match="MarchChandrupatla"):
        driver.configuration(_march("march_chandrupatla"))


def test_march_chandrupatla_is_not_offered_and_not_run_as_bisection(nb):
    """The runner never reaches the kernels with scipy's refiner: the method is not offered
    (``prepare`` refuses it: the run records the configuration as skipped), and solving it
    directly is an error, not a bisection."""
    scene, o, d = _scene("sphere")
    assert "march_chandrupatla" not in nb.methods()
    with pytest.raises(NotImplementedError, match="does not implement"):
        nb.prepare("march_chandrupatla", scene, o, d, t_max=10.0)
    knobs = METHODS["march_chandrupatla"].validate({})
    with pytest.raises(NotImplementedError, match="MarchChandrupatla"):
        nb.solve("march_chandrupatla", scene, o, d, t_min=0.0, t_max=10.0, **knobs)


def test_each_step_is_written_once_and_both_kernels_are_generated_from_it():
    """The one-ray kernel and the lanes kernel hold every line of the step templates (with the
    ray's variables renamed: no suffix, ``_0`` … for the lanes), and the steps' arithmetic
    appears nowhere else in the package: no hand-kept copy of a step remains."""
    import re
    from pathlib import Path

    from impls.numba import template

    one, lanes = template.one_ray_source(), template.lanes_source()
    for name in ("START", "STEP", "LADDER"):
        for line in getattr(template, name).strip("\n").splitlines():
            line = line.strip()
            if line.startswith("@EVAL"):
                continue
            assert re.sub(r"_K\b", "", line) in one, (name, line)
            if name != "LADDER":  # (the lanes kernel has no ladder stage)
                for k in range(template.LANES):
                    assert re.sub(r"_K\b", f"_{k}", line) in lanes, (name, k, line)
    # (one φ per lane, and φ with dφ/dt for Newton's refinement: every refiner runs in the lanes)
    assert lanes.count("= ev(p, ") == template.LANES and lanes.count("= ev_d(p, ") == template.LANES
    # the march step, the crossing test, the secant and chord, the safeguard's lengthened step, the
    # closed-bracket test: in the templates, and in no other module of the package
    arithmetic = [r"_min\(\w+ \+ step", r"\(\w+ > 0\) != \(\w+ > 0\)", r"\w+ - \w+ \* \(\w+ - \w+\) / \(\w+ - \w+\)",
                  r"\w+ \+ 0\.5 \* hh", r"<= xtol\) or \(\w+ <= \w+\) or \(\w+ >= \w+\)"]
    steps = template.START + template.STEP + template.LADDER
    for pattern in arithmetic:
        assert re.search(pattern, steps), pattern
        for path in Path(template.__file__).parent.glob("*.py"):
            if path.name != "template.py":
                assert not re.search(pattern, path.read_text()), (pattern, path.name)
