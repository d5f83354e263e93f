"""Third-party backends plug in without editing isobench: by ``module:attr`` spec and by entry
point, and the plug-in is run through the *same* conformance suite as the built-ins."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from impls import Backend, registry
from tests.conftest import HANG_GUARD_S

SPEC = "tests.plugin_backend:PluginBackend"
ROOT = Path(__file__).resolve().parents[1]


def test_spec_resolves_to_a_backend():
    b = registry.resolve(SPEC)
    assert not isinstance(b, registry.Unavailable), b
    assert isinstance(b, Backend) and b.id == "npwrap" and "sphere_trace" in b.methods()


def test_entry_point_is_found(tmp_path, monkeypatch):
    """An installed distribution declaring ``[isobench.backends] npwrap = …`` (a dist-info folder on
    sys.path is what pip install writes)."""
    dist = tmp_path / "npwrap_plugin-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: npwrap-plugin\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text(f"[{registry.ENTRY_POINT_GROUP}]\nnpwrap = {SPEC}\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert "npwrap" in registry.default_ids()
    b = registry.resolve("npwrap")
    assert not isinstance(b, registry.Unavailable), b
    assert b.id == "npwrap"


def test_broken_plugin_is_reported_not_fatal():
    b = registry.resolve("tests.plugin_backend:NoSuchAttr")
    assert isinstance(b, registry.Unavailable) and "NoSuchAttr" in b.reason


@pytest.mark.slow  # a second pytest session
def test_plugin_passes_the_conformance_suite():
    """Run tests/conformance/ for the plug-in only, in a fresh interpreter."""
    env = dict(os.environ, ISOBENCH_EXTRA_BACKENDS=SPEC)
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "tests/conformance/",
         "-k", "PluginBackend", "-W", "ignore::RuntimeWarning"],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=HANG_GUARD_S,
    )
    tail = proc.stdout[-3000:] + proc.stderr[-2000:]
    assert proc.returncode == 0, tail
    # "1 xfailed" (an expected failure listed with its reason) is not a failure
    assert " passed" in proc.stdout and not re.search(r"\d+ failed", proc.stdout), tail


def test_extra_backends_come_from_the_environment():
    from tests.conftest import extra_backend_ids

    assert extra_backend_ids(" a.b:C, ,d.e:F ") == ["a.b:C", "d.e:F"]
    assert extra_backend_ids("") == []


def test_broken_builtin_backend_fails_instead_of_skipping(monkeypatch):
    """A built-in whose library is installed but which resolves to Unavailable (e.g. a syntax
    error under impls/) must fail the backend tests, not silently skip them."""
    from tests import conftest

    monkeypatch.setattr(registry, "resolve", lambda bid: registry.Unavailable(bid, "SyntaxError: planted"))
    with pytest.raises(pytest.fail.Exception, match="installed but failed to load.*planted"):
        conftest.resolve_or_skip("numpy")
    with pytest.raises(pytest.skip.Exception, match="planted"):
        conftest.resolve_or_skip("some.plugin:Backend")
