"""Shared fixtures: every registered backend, as a parameter (unavailable ones are skipped)."""

from __future__ import annotations

import os

import pytest
from hypothesis import settings

from impls import registry

# CI runs hypothesis derandomized so a red build is reproducible.
settings.register_profile("ci", derandomize=True, deadline=None, max_examples=60)
settings.register_profile("dev", deadline=None, max_examples=60)
settings.load_profile("ci" if os.environ.get("CI") else "dev")

BACKEND_IDS = registry.default_ids()


@pytest.fixture(scope="session", params=BACKEND_IDS)
def backend(request):
    b = registry.resolve(request.param)
    if isinstance(b, registry.Unavailable):
        pytest.skip(b.reason)
    return b
