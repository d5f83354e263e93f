"""Compiled kernels are kept between runs in one cache directory (``--cache-dir``, default
``$XDG_CACHE_HOME/isobench``; ``--no-cache`` for a cold start): each row says whether its kernel
was compiled or reused, and reusing changes no result."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bench.run.environment import default_cache_dir
from bench.run.results import read_results
from tests.conftest import bench_cli

#: what must be identical whether a kernel was compiled or came from the cache
SAME = ["case_id", "backend", "method", "knob", "quantity", "outcome", "status_counts", "error_max", "error_p99",
        "n_false_hit", "n_false_miss", "evals_per_ray", "iterations_max"]


def test_default_cache_dir_follows_xdg(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert default_cache_dir() == tmp_path / "isobench"
    monkeypatch.delenv("XDG_CACHE_HOME")
    assert default_cache_dir().parts[-2:] == (".cache", "isobench")


@pytest.mark.slow  # three runs that compile jax and numba kernels
def test_a_second_run_reuses_every_kernel_and_no_cache_compiles_afresh(tmp_path):
    cache = tmp_path / "cache"
    args = ["--case", "torus.camera.32x32", "--method", "hybrid_secant,sphere_trace", "--accuracy-only", "--no-claims",
            "--no-progress"]
    from impls import registry

    backends = [b for b in ("jax:cpu", "numba") if not isinstance(registry.resolve(b), registry.Unavailable)]
    if not backends:
        pytest.skip("neither jax nor numba is installed")
    args += ["--backend", ",".join(backends)]
    runs = {}
    for name, extra in (("cold", ["--cache-dir", cache]), ("warm", ["--cache-dir", cache]), ("none", ["--no-cache"])):
        p = bench_cli("run", "--out", tmp_path / name, *extra, *args)
        assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
        runs[name] = read_results(tmp_path / name).sort_values(SAME[:5]).reset_index(drop=True)
        env = json.loads((tmp_path / name / "environment.json").read_text())
        assert env["cache_dir"] == (str(cache.resolve()) if name != "none" else "none (--no-cache)")
    ok = {k: df[df["outcome"] == "ok"] for k, df in runs.items()}
    assert len(ok["cold"]) and set(ok["cold"]["backend"]) == set(backends)
    # cold: each backend compiles (numba once per scene structure and kernel, reused by the other
    # knob settings and by the other method sharing the kernel: the certified methods evaluate φ
    # with one kernel; jax once per method and structure, the knob settings sharing it: knobs traced)
    cold = ok["cold"].groupby(["backend"])["compile_cache"].agg(set)
    assert all("compiled" in v and v <= {"compiled", "reused"} for v in cold), cold
    if "jax:cpu" in backends:
        jax_cold = ok["cold"][ok["cold"]["backend"] == "jax:cpu"].drop_duplicates(["method", "knob"])
        per_method = jax_cold.groupby("method")["compile_cache"].agg(list)
        # each method compiles; its settings that differ only in traced knobs (the tolerance
        # sweeps) reuse a kernel compiled for another setting
        assert all("compiled" in v and "reused" in v for v in per_method), per_method
    assert set(ok["warm"]["compile_cache"]) == {"reused"}, ok["warm"][["backend", "method", "compile_cache"]]
    # --no-cache: nothing from disk; numba compiles (and reuses within the run); jax states only
    # the reuse of a kernel this run compiled (whether a fresh compile hit a cache it cannot say)
    none = ok["none"]
    assert set(none.loc[none["backend"] == "jax:cpu", "compile_cache"].dropna()) <= {"reused"}
    assert "compiled" in set(none.loc[none["backend"] == "numba", "compile_cache"]) or "numba" not in backends
    for name in ("warm", "none"):
        a, b = runs["cold"][SAME], runs[name][SAME]
        assert a.equals(b), (name, a.compare(b))
    assert (cache / "jax").is_dir() or "jax:cpu" not in backends
    assert any((cache / "numba").glob("*.py")) or "numba" not in backends


#: a numba function kept on disk through impls.cache.lock_numba_cache, in its own module file
_CACHED_MODULE = """
from numba import njit
from impls.cache import lock_numba_cache

def total(x):
    s = x[0] * 0
    for i in range(x.shape[0]):
        s += x[i] * 2
    return s

total_jit = njit(total)
lock_numba_cache(total_jit)
"""

#: a process that calls the cached function on one dtype; PAUSE_READ / PAUSE_WRITE put pauses into
#: numba's index update (IndexDataCacheFile.save, numba 0.68) between its index read and its index
#: write, and between its index write and its data write: the windows where another process's
#: update interleaves on a loaded machine
_CALLER = """
import itertools, json, os, sys, time
import numpy as np
from numba.core import caching

def paused_save(self, key, data):
    overloads = self._load_index()
    time.sleep(float(os.environ.get("PAUSE_READ", "0")))
    try:
        data_name = overloads[key]
    except KeyError:
        existing = set(overloads.values())
        data_name = next(self._data_name(i) for i in itertools.count(1) if self._data_name(i) not in existing)
        overloads[key] = data_name
        self._save_index(overloads)
    time.sleep(float(os.environ.get("PAUSE_WRITE", "0")))
    self._save_data(data_name, data)

caching.IndexDataCacheFile.save = paused_save
sys.path.insert(0, sys.argv[1])
import cached_total
x = np.arange(10, dtype=sys.argv[2])
print(json.dumps({"total": float(cached_total.total_jit(x)),
                  "hits": sum(cached_total.total_jit.stats.cache_hits.values())}))
"""


def _call_cached(where, dtype, **pauses):
    import os
    import subprocess
    import sys

    from tests.conftest import ROOT

    env = {**os.environ, "PYTHONPATH": str(ROOT), **{k: str(v) for k, v in pauses.items()}}
    return subprocess.Popen([sys.executable, str(where / "caller.py"), str(where), dtype], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _result(proc) -> dict:
    out, err = proc.communicate()
    assert proc.returncode == 0, err[-3000:]
    return json.loads(out.strip().splitlines()[-1])


def _cached_module(tmp_path):
    pytest.importorskip("numba")
    (tmp_path / "cached_total.py").write_text(_CACHED_MODULE)
    (tmp_path / "caller.py").write_text(_CALLER)
    return tmp_path


@pytest.mark.slow  # fresh processes that compile numba kernels, two of them paused (tests/conftest.py: COMPILING_LIBS)
def test_numba_kernels_compiled_at_once_by_two_processes_load_their_own_code(tmp_path):
    """Two processes compile two signatures of one cached function at once, with numba's index
    update paused where a loaded machine interleaves it (without the lock, the int64 entry ends up
    holding the float64 machine code, and a later int64 call returns 4.45e-322, not 90); then each
    signature, loaded from disk in a fresh process, gives its own answer."""
    where = _cached_module(tmp_path)
    first = _call_cached(where, "float64", PAUSE_READ=2, PAUSE_WRITE=2)
    second = _call_cached(where, "int64", PAUSE_READ=2.5)
    assert _result(first)["total"] == 90 and _result(second)["total"] == 90
    for dtype in ("float64", "int64"):
        again = _result(_call_cached(where, dtype))
        assert again == {"total": 90, "hits": 1}, (dtype, again)


@pytest.mark.slow  # fresh processes that compile numba kernels (tests/conftest.py: COMPILING_LIBS)
def test_a_numba_cache_entry_of_another_signature_is_compiled_afresh(tmp_path):
    """An index that maps one signature to another's code (what an unlocked concurrent update
    leaves, or a cache written by an older isobench) is not run: the entry's own signature is
    checked on load, and the function compiles afresh."""
    import pickle

    where = _cached_module(tmp_path)
    for dtype in ("float64", "int64"):
        assert _result(_call_cached(where, dtype))["total"] == 90
    (index,) = (where / "__pycache__").glob("cached_total.total-*.nbi")
    with open(index, "rb") as f:
        version = pickle.load(f)
        stamp, overloads = pickle.loads(f.read())
    by_dtype = {str(k[0][0].dtype): name for k, name in overloads.items()}
    assert set(by_dtype) == {"float64", "int64"}, overloads
    swapped = {k: by_dtype["float64"] if str(k[0][0].dtype) == "int64" else name for k, name in overloads.items()}
    with open(index, "wb") as f:
        pickle.dump(version, f, protocol=-1)
        f.write(pickle.dumps((stamp, swapped), protocol=-1))
    assert _result(_call_cached(where, "int64")) == {"total": 90, "hits": 0}
    assert _result(_call_cached(where, "float64")) == {"total": 90, "hits": 1}
    assert _result(_call_cached(where, "int64")) == {"total": 90, "hits": 1}


#: march_newton on numba and numpy for the scenes named on the command line (one process, the
#: kernels from the cache directory in ISOBENCH_CACHE_DIR); prints {scene: numba's hits and depths
#: are numpy's}
_TWO_SCENES = """
import json, sys
import numpy as np
from reference.csg import Intersection, Union
from reference.primitives import Box, Sphere
from impls.registry import resolve

scenes = {"union": Union(Sphere(radius=0.8), Box((0.6, 0.6, 0.6))),
          "intersection": Intersection(Sphere(radius=0.8), Box((0.6, 0.6, 0.6)))}
rng = np.random.default_rng(0)
o = np.tile([0.0, 0.0, 3.0], (256, 1))
d = rng.normal(size=(256, 3)) * [0.15, 0.15, 0.0] + [0.0, 0.0, -1.0]
d /= np.linalg.norm(d, axis=1, keepdims=True)
out = {}
for name in sys.argv[1:]:
    t = {b: np.asarray(resolve(b).prepare("march_newton", scenes[name], o, d, t_min=0.0, t_max=10.0, step=0.01,
                                          xtol=1e-12, max_steps=4096).run()["t"]) for b in ("numba", "numpy")}
    hit = np.isfinite(t["numpy"])
    out[name] = bool(np.array_equal(np.isfinite(t["numba"]), hit) and np.abs(t["numba"][hit] - t["numpy"][hit]).max() < 1e-9)
print(json.dumps(out))
"""


@pytest.mark.slow  # four processes that compile or load numba kernels
def test_numba_kernels_of_two_scenes_from_two_processes_run_their_own_scene(tmp_path):
    """Two scene structures' march_newton kernels, each compiled by its own process, then both
    loaded from the disk cache by one process: each runs its own φ.  (numba names compiled code by
    module, qualified name and a per-process counter, and links cached code by those names; the
    scenes' φ-derivative closures once had one name in both processes, and the process that loaded
    both ran the first scene's φ in the second's kernel: CI's csg.union march_newton row, 642 false
    misses after csg.shell's kernel.)"""
    import os
    import subprocess
    import sys

    from tests.conftest import ROOT

    pytest.importorskip("numba")
    (tmp_path / "two_scenes.py").write_text(_TWO_SCENES)
    env = {**os.environ, "PYTHONPATH": str(ROOT), "ISOBENCH_CACHE_DIR": str(tmp_path / "cache")}

    def run(*names):
        p = subprocess.run([sys.executable, str(tmp_path / "two_scenes.py"), *names], env=env, capture_output=True,
                           text=True)
        assert p.returncode == 0, p.stderr[-3000:]
        return json.loads(p.stdout.strip().splitlines()[-1])

    assert run("union") == {"union": True}
    assert run("intersection") == {"intersection": True}
    assert run("union", "intersection") == {"union": True, "intersection": True}
    assert run("intersection", "union") == {"intersection": True, "union": True}


def test_numerical_first_hits_are_kept_in_the_cache_directory_by_case_and_code(tmp_path, monkeypatch):
    """bench keeps a case's numerical first hits (a scene without closed-form hits) under the
    reference cache: a second case object with the same scene and rays reads them, bit for bit,
    without the numerical reference; other rays are another entry."""
    import dataclasses

    from bench.run.references import load_numerical_hits
    from reference.cases import Case, get_case

    base = get_case("mlp.camera.32x32")
    case = Case("mlp.test", base.scene, base.origins[::97], base.directions[::97], base.t_min, base.t_max)
    assert not case.scene.info.exact_hits
    load_numerical_hits(case, tmp_path)
    (entry,) = tmp_path.glob("first_hit-*.npz")
    want, bounds = case.exact_t, case.exact_t_error_bounds
    assert np.isfinite(want).any()

    again = dataclasses.replace(case)
    monkeypatch.setattr(Case, "numerical_hits", lambda self: pytest.fail("computed although the cache holds it"))
    load_numerical_hits(again, tmp_path)
    np.testing.assert_array_equal(again.exact_t, want)
    np.testing.assert_array_equal(again.exact_t_error_bounds, bounds)
    monkeypatch.undo()

    other = dataclasses.replace(case, origins=case.origins[1:], directions=case.directions[1:])
    load_numerical_hits(other, tmp_path)
    assert len(list(tmp_path.glob("first_hit-*.npz"))) == 2
    # a damaged entry is computed again (and rewritten), not an error
    entry.write_bytes(b"not an npz")
    fresh = dataclasses.replace(case)
    load_numerical_hits(fresh, tmp_path)
    np.testing.assert_array_equal(fresh.exact_t, want)
    # a scene with closed-form hits has nothing to keep
    load_numerical_hits(get_case("torus.camera.32x32"), tmp_path)
    assert len(list(tmp_path.glob("first_hit-*.npz"))) == 2


def test_a_claims_integral_is_kept_by_all_of_its_inputs(tmp_path, monkeypatch):
    """render_exact_kept computes the rendering integral once per inputs: the same inputs read the
    stored answer bit for bit, without render_exact; another sharpness or ray is another entry."""
    from bench.run.references import render_exact_kept
    from reference import Sphere, rendering

    scene, rho = Sphere(), rendering.SineColor()
    o, d = np.array([[0.0, 0.0, 3.0]]), np.array([[0.0, 0.0, -1.0]])
    want = render_exact_kept(tmp_path, scene, rho, "neus", 50.0, o, d, 1.5, 2.5)
    np.testing.assert_array_equal(want[0], rendering.render_exact(scene, rho, "neus", 50.0, o, d, 1.5, 2.5)[0])
    monkeypatch.setattr(rendering, "render_exact", lambda *a, **k: pytest.fail("computed although it is kept"))
    got = render_exact_kept(tmp_path, scene, rho, "neus", 50.0, o, d, 1.5, 2.5)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])
    monkeypatch.undo()
    render_exact_kept(tmp_path, scene, rho, "neus", 60.0, o, d, 1.5, 2.5)
    render_exact_kept(tmp_path, scene, rho, "neus", 50.0, o, d * -1.0, 1.5, 2.5)
    assert len(list(tmp_path.glob("render_exact-kept-*.npz"))) == 3


def test_a_cases_kept_rendering_integral_is_keyed_by_its_colour_field_too(tmp_path):
    """The run's rendering integral (``exact_color``) is kept by the case's version, which holds
    the scene and rays but not the colour field: a case given another ``color_frequency`` (same
    id, scene and rays) read the old field's colours back.  The field's repr is in the key."""
    import dataclasses

    from bench.run.references import ReferenceOptions, exact_color
    from impls.methods import get_method
    from reference import Sphere, rays
    from reference.cases import Case

    o, d = rays.pinhole(eye=(0.0, 0.0, 3.0), look_at=(0.0, 0.0, 0.0), fov_deg=20.0, width=2, height=2)
    case = Case(id="tests.colour.kept", scene=Sphere(), origins=o, directions=d, t_min=0.0, t_max=6.0)
    spec = get_method("volume_nerf_uniform")
    knobs = spec.validate({})
    opts = {"_options": ReferenceOptions(expensive=True, disk=tmp_path)}
    two = exact_color(case, spec, knobs, dict(opts))[0]
    five_case = dataclasses.replace(case, color_frequency=5.0)
    five = exact_color(five_case, spec, knobs, dict(opts))[0]
    fresh = exact_color(five_case, spec, knobs, {"_options": ReferenceOptions(expensive=True, disk=None)})[0]
    np.testing.assert_array_equal(five, fresh)
    assert not np.allclose(two, five)
    assert len(list(tmp_path.glob("render_exact-*.npz"))) == 2
