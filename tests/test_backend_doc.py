"""docs/backends.md tells the truth: its example backend, written outside the repository, passes
``python -m bench conformance``; the protocol it documents is the one the runner calls (a backend
written to an older, wrong ``synchronize()`` fails, with a message naming ``synchronize(out)``);
every member of :class:`impls.protocol.Backend` and every status is documented; a plug-in is
named by its own id."""

from __future__ import annotations

import inspect
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from impls import Status
from impls.protocol import Backend
from tests.conftest import HANG_GUARD_S

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "docs" / "backends.md"


def example_source() -> str:
    """The example backend: the fenced python block after the ``<!-- example: my_backend.py``
    marker of docs/backends.md."""
    text = DOC.read_text(encoding="utf-8")
    m = re.search(r"<!-- example: my_backend\.py.*?-->\s*```python\n(.*?)```", text, re.S)
    assert m, "docs/backends.md lost its example backend (the '<!-- example: my_backend.py' block)"
    return m.group(1)


def write_example(directory: Path, source: str | None = None) -> Path:
    assert ROOT not in directory.resolve().parents, "the example must be written outside the repository"
    (directory / "my_backend.py").write_text(source if source is not None else example_source(), encoding="utf-8")
    return directory


def conformance(directory: Path, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(directory), str(ROOT)])}
    env.pop("ISOBENCH_EXTRA_BACKENDS", None)
    return subprocess.run([sys.executable, "-m", "bench", "conformance", "--backend", "my_backend:MyBackend", *args],
                          cwd=directory, env=env, capture_output=True, text=True, timeout=HANG_GUARD_S)


def test_the_documented_example_passes_conformance(tmp_path):
    p = conformance(write_example(tmp_path))
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    out = p.stdout
    assert "PASSED   test_normal_against_exact[my_backend:MyBackend-sphere]" in out
    assert "PASSED   test_flagged_rays_are_nan_and_agree_with_numpy[my_backend:MyBackend-normal]" in out
    assert "FAILED" not in out
    counts = re.search(r"mine: (\d+) passed, (\d+) failed, (\d+) skipped", out)
    assert counts and int(counts.group(1)) >= 5 and counts.group(2) == "0", out[-2000:]
    assert "does not offer sphere_trace" in out  # what was not checked is said, not hidden


def _without_out(source: str) -> str:
    old = "    def synchronize(self, out) -> None:"
    assert old in source
    return source.replace(old, "    def synchronize(self) -> None:")


def test_a_backend_with_synchronize_without_out_fails_conformance(tmp_path):
    p = conformance(write_example(tmp_path, _without_out(example_source())), "--select", "normal_against_exact")
    assert p.returncode == 1, p.stdout[-3000:] + p.stderr[-3000:]
    assert "FAILED   test_normal_against_exact" in p.stdout and "does not conform" in p.stderr


def test_the_runner_names_synchronize_out_for_such_a_backend(tmp_path):
    from bench.run.configuration import Config, run_one
    from bench.run.timing import TimingPolicy
    from reference import get_case

    namespace: dict = {}
    exec(compile(_without_out(example_source()), "my_backend.py", "exec"), namespace)
    case = get_case("sphere.camera.64x64")
    rows = run_one("r", Config(case, "mine", "normal", "float64", {}), namespace["MyBackend"](),
                   TimingPolicy(accuracy_only=True), float("nan"))
    assert rows[0]["outcome"] == "failed" and "synchronize(out)" in rows[0]["reason"], rows[0]
    namespace.clear()
    exec(compile(example_source(), "my_backend.py", "exec"), namespace)
    rows = run_one("r", Config(case, "mine", "normal", "float64", {}), namespace["MyBackend"](),
                   TimingPolicy(accuracy_only=True), float("nan"))
    assert {r["outcome"] for r in rows} == {"ok"}, rows[0].get("reason")
    assert np.isfinite([r["error_max"] for r in rows]).all()


def test_every_protocol_member_and_status_is_documented():
    text = DOC.read_text(encoding="utf-8")
    members = [n for n in Backend.__dict__ if not n.startswith("_")] + list(Backend.__annotations__)
    for name in set(members) | {"declines"}:
        assert f"| `{name}" in text, f"docs/backends.md does not document Backend.{name}"
    # the documented signature of synchronize is the protocol's
    params = list(inspect.signature(Backend.synchronize).parameters)[1:]
    assert params == ["out"] and "| `synchronize(out)` | `(out) -> None` |" in text
    for s in Status:
        if s != Status.IN_PROGRESS:
            assert f"| `{s.name}` |" in text and f"| {int(s)} |" in text.replace("| −", "| -"), s.name


def test_a_plugin_is_named_by_its_id():
    from bench.commands._common import resolve_backends

    specs: dict = {}
    backends, msg = resolve_backends(["tests.plugin_backend:PluginBackend", "numpy"], 1, specs=specs)
    assert msg == "" and list(backends) == ["npwrap", "numpy"]
    assert specs == {"npwrap": "tests.plugin_backend:PluginBackend", "numpy": "numpy"}
    backends, msg = resolve_backends(["tests.plugin_backend:PluginBackend", "tests.plugin_backend:PluginBackend"], 1)
    assert backends is None and "both name the backend 'npwrap'" in msg


@pytest.mark.parametrize("where", ["README.md", "docs/backends.md"])
def test_the_conformance_command_is_documented(where):
    text = (ROOT / where).read_text(encoding="utf-8")
    assert "python -m bench conformance --backend" in text and "ISOBENCH_EXTRA_BACKENDS" in text


@pytest.mark.slow  # jax's checks are in the slow tier (tests/conftest.py, COMPILING_LIBS)
def test_fast_keeps_a_compiling_backends_quick_checks():
    """``--fast`` leaves out the checks marked slow themselves, not every check of jax or numba.

    tests/conftest.py marks all of a compiling backend's checks slow (for ``pytest -m "not
    slow"``); read as ``-m "not slow"``, ``--fast`` on ``jax:gpu`` once selected nothing at all."""
    pytest.importorskip("jax")
    env = {k: v for k, v in os.environ.items() if k != "ISOBENCH_EXTRA_BACKENDS"}
    p = subprocess.run([sys.executable, "-m", "bench", "conformance", "--backend", "jax:cpu", "--fast", "--select",
                        "raycast_is_offered or ray_bounds_clip"], cwd=ROOT, env=env, capture_output=True, text=True,
                       timeout=HANG_GUARD_S)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    assert "PASSED   test_raycast_is_offered_by_no_array_library_backend[jax:cpu]" in p.stdout
    assert "ray_bounds_clip" not in p.stdout  # marked slow itself: left out by --fast
