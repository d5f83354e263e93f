"""The backends every check of the conformance suite runs on: built-ins, entry points, and plug-in
specs from the environment (``ISOBENCH_EXTRA_BACKENDS``, tests/conftest.py)."""

from __future__ import annotations

import pytest

from tests.conftest import BACKEND_IDS, backend_params, resolve_or_skip


@pytest.fixture(scope="module", params=backend_params(BACKEND_IDS))
def any_backend(request):
    return resolve_or_skip(request.param)

