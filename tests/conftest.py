"""Shared fixtures: every registered backend, as a parameter.

``BACKEND_IDS`` = the registry's default ids (built-ins, accelerators present, entry points) plus
the comma-separated ``pkg.mod:attr`` specs in ``ISOBENCH_EXTRA_BACKENDS`` (how a plug-in is run
through the conformance suite without editing isobench).  An unavailable backend is skipped with
its reason — except a *built-in* whose library is installed: then ``Unavailable`` means isobench
itself is broken (e.g. a syntax error under ``impls/``), and that is a test failure, not a skip.
"""

from __future__ import annotations

import importlib.util
import os

import pytest
from hypothesis import settings

from impls import registry
from impls.protocol import Declined

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
    return b


@pytest.fixture(scope="session", params=BACKEND_IDS)
def backend(request):
    return resolve_or_skip(request.param)
