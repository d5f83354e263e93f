"""Shared fixtures: every registered backend, as a parameter.

``BACKEND_IDS`` = the registry's default ids (built-ins, accelerators present, entry points) plus
the comma-separated ``pkg.mod:attr`` specs in ``ISOBENCH_EXTRA_BACKENDS`` (how a plug-in is run
through the conformance suite without editing isobench).  An unavailable backend is skipped with
its reason — except a *built-in* whose library is installed: then ``Unavailable`` means isobench
itself is broken (e.g. a syntax error under ``impls/``), and that is a test failure, not a skip.
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from filelock import FileLock
from hypothesis import settings

from bench.run.environment import configure_caches, configure_threads, default_cache_dir, untimed_backend

# one thread per library, OpenMP threads waiting passively, as the bench commands run (set before
# torch, jax or a BLAS starts its thread pool): pytest-xdist already runs one worker per core, and
# more threads per worker only fight over the cores (10-20× slower torch under load;
# CHANGELOG.md, "torch under load")
configure_threads(1)

# compiled kernels (jax, numba) kept in the user's isobench cache directory, as the bench commands
# keep them (and the commands the tests start use the same one by default): the session's
# processes share them, and a later session reuses them.  Set before any backend is imported.
if "ISOBENCH_CACHE_DIR" not in os.environ:
    configure_caches(default_cache_dir())

from impls import registry  # noqa: E402
from impls.protocol import Declined  # noqa: E402

# CI runs hypothesis derandomized so a red build is reproducible.
settings.register_profile("ci", derandomize=True, deadline=None, max_examples=60)
settings.register_profile("dev", deadline=None, max_examples=60)
settings.load_profile("ci" if os.environ.get("CI") else "dev")

EXTRA_ENV = "ISOBENCH_EXTRA_BACKENDS"
BUILTIN_LIBS = ("numpy", "torch", "jax")


def extra_backend_ids(value: str | None = None) -> list[str]:
    """The plug-in specs of ``ISOBENCH_EXTRA_BACKENDS`` (comma-separated, blanks ignored)."""
    value = os.environ.get(EXTRA_ENV, "") if value is None else value
    return [s.strip() for s in value.split(",") if s.strip()]


BACKEND_IDS = list(dict.fromkeys(registry.default_ids() + extra_backend_ids()))

#: libraries whose every test configuration compiles kernels (XLA, LLVM): the tests parametrized
#: over backends run them in the slow tier (CI's whole gate), so `-m "not slow"` checks the
#: eager backends only
COMPILING_LIBS = ("jax", "numba")


def backend_params(ids: list[str]) -> list:
    """``ids`` as pytest parameters, those of :data:`COMPILING_LIBS` marked slow."""
    return [pytest.param(b, marks=pytest.mark.slow) if b.split(":")[0] in COMPILING_LIBS else b for b in ids]

ROOT = Path(__file__).resolve().parent.parent

#: the limit on a child process the tests start: a guard against a process that hangs, not a
#: measure of speed.  Far beyond what any of these commands needs on a loaded machine, so no test
#: result depends on the machine's speed (DESIGN.md: "No test depends on the machine's speed").
HANG_GUARD_S = 3 * 3600.0


def bench_cli(*args, cwd=None, env=None) -> subprocess.CompletedProcess:
    """``python -m bench ARGS`` in a fresh interpreter, output captured (only a hang is bounded)."""
    return subprocess.run([sys.executable, "-m", "bench", *map(str, args)], cwd=cwd or ROOT, env=env,
                          capture_output=True, text=True, timeout=HANG_GUARD_S)


def _shared_dir(tmp_path_factory, worker_id: str) -> Path:
    """A folder shared by every process of this pytest session: the session's base temporary
    folder, or under pytest-xdist the parent of the workers' ones (one per session, not shared
    with other sessions)."""
    base = tmp_path_factory.getbasetemp()
    return base if worker_id == "master" else base.parent


def shared_run(tmp_path_factory, worker_id: str, name: str, *args) -> tuple[Path, str]:
    """Run ``python -m bench run --out DIR ARGS`` once per pytest session, whichever test file
    or xdist worker asks first, and share it: the others wait on a file lock and read what the
    first wrote (the run directory and its stdout).  Returns ``(DIR, stdout)``; a failed run
    fails every test that uses it, with its output."""
    root = _shared_dir(tmp_path_factory, worker_id)
    out, record = root / f"shared-{name}", root / f"shared-{name}.json"
    with FileLock(str(root / f"shared-{name}.lock")):
        if not record.exists():
            p = bench_cli("run", "--out", out, *args)
            record.write_text(json.dumps({"returncode": p.returncode, "stdout": p.stdout, "stderr": p.stderr}))
    got = json.loads(record.read_text())
    assert got["returncode"] == 0, got["stdout"][-5000:] + got["stderr"][-5000:]
    return out, got["stdout"]


#: the quick suite as CI runs it in the tests: every backend, every configuration of its plan and
#: its stability stage, the report, no claims; accuracy only (one call per configuration).  What the
#: tests check of it is the plan's coverage, the files, the report's sections and the accuracy gate
#: against reports/baseline, none of which reads a timing sample; the timing protocol has tests of
#: its own (tests/test_timing.py; timed runs in tests/test_bench_runner.py).  Measured back to back
#: on 2 cores, warm cache: 145 s wall, 269 CPU-s timed (--min-time 0.02 --min-repeats 3) → 115 s,
#: 170 CPU-s.
QUICK_ARGS = ("--suite", "quick", "--accuracy-only", "--no-claims")


@pytest.fixture(scope="session")
def quick_run_and_stdout(tmp_path_factory, worker_id):
    """The quick suite run once per session (stdout piped, as in CI: progress comes as lines)."""
    return shared_run(tmp_path_factory, worker_id, "quick", *QUICK_ARGS)


@pytest.fixture(scope="session")
def quick_run(quick_run_and_stdout):
    return quick_run_and_stdout[0]


@pytest.hookimpl(wrapper=True)
def pytest_pyfunc_call(pyfuncitem):
    """A backend that declines a test's scene (:class:`impls.protocol.Declined`, e.g. the numba
    backend and a user's field it does not compile) skips that test with its reason, as a run
    records a skipped row: declining is part of the protocol, not a failure.  Tests that check
    declining itself catch the exception inside the test."""
    try:
        return (yield)
    except Declined as exc:
        pytest.skip(f"declined: {exc}")


def resolve_or_skip(backend_id: str):
    """The backend for ``backend_id``; skip if unavailable, fail if a built-in is installed but broken."""
    b = registry.resolve(backend_id)
    if isinstance(b, registry.Unavailable):
        lib = backend_id.split(":")[0]
        if lib in BUILTIN_LIBS and importlib.util.find_spec(lib) is not None:
            pytest.fail(f"built-in backend {backend_id} is installed but failed to load: {b.reason}", pytrace=False)
        pytest.skip(b.reason)
    return untimed_backend(b) if backend_id.split(":")[0] in UNTIMED_LIBS else b


#: libraries whose backends the tests take in the configuration of a run that times nothing
#: (:func:`bench.run.environment.untimed_backend`, as the stability stage does): jax's then runs one
#: compaction level per chunk, the same per-ray results (tests/test_driver.py checks them against
#: every level setting) at about a third of the compile (its timed runs' levels are each a copy of
#: every stage's loop: docs/performance.md); measured on test_roots.py and test_rootfind_certified.py
#: -k jax with an empty cache, 286 → 184 s.  The timed levels stay covered: tests/test_driver.py
#: builds its own settings, and the 256² mesh test (test_certified_at_scale.py) takes jax's timed
#: backend.  (The shared quick-suite run is accuracy-only, so it too runs the untimed settings.)
#: Not numba: its untimed configuration leaves out the marcher kernels the tests check.
UNTIMED_LIBS = ("jax",)


def require_method(backend, method: str) -> None:
    """Skip, with the reason, where ``backend`` does not offer ``method`` (an engine offers only
    ``raycast``; a compiled plug-in declines what it does not compile)."""
    if method not in backend.methods():
        pytest.skip(f"{backend.id} does not offer {method}")


@pytest.fixture(scope="session", params=backend_params(BACKEND_IDS))
def backend(request):
    return resolve_or_skip(request.param)


#: the test files that take longest (measured per test on 2 cores, warm cache, 2026-12-01: the
#: shared quick-suite run, the 256² checks, the subprocess and compiling tests), longest first.
#: Under ``-n auto --dist loadfile`` a file runs whole on one worker, in collection order: a
#: long file collected late (test_cli.py sorts mid-list) starts when the others are nearly done and
#: leaves the other workers idle until it ends.  Started first, the long files run beside the many
#: short ones.  (Only the order changes; every file still runs whole, its own tests in order.)  For
#: the same reason the conformance suite is a folder of files (tests/conformance/), not one file.
LONGEST_FILES = ("test_certified_at_scale.py", "test_cli.py", "test_crash_isolation.py", "test_compile_cache.py",
                 "test_rootfind_certified.py", "test_step_field.py", "test_cluster.py", "test_jax_kernel_store.py",
                 "test_plugin.py", "test_claims_checks.py", "test_driver.py", "test_rootfind_marching.py",
                 "test_renderers.py", "test_reference_bounds.py", "test_bench_resume.py", "test_jax_kernel_reuse.py",
                 "test_reference_depth_bound.py", "test_ray_bounds.py", "test_roots.py", "test_every_method.py")


def pytest_configure(config):
    # pytest-xdist (≥ 3.6) queues files by their number of tests unless told not to: keep the order
    # below, which is by time (test_cli.py's 44 tests include the quick-suite run)
    if hasattr(config.option, "loadscopereorder"):
        config.option.loadscopereorder = False


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(LONGEST_FILES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: a file's tests keep their order
