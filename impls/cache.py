"""Where the backends keep what they compile between runs.

The bench commands choose one cache directory (``--cache-dir``, default
``$XDG_CACHE_HOME/isobench``; ``--no-cache``: none) and hand it to the backends in the
environment variable :data:`CACHE_ENV`, set before any backend is imported; each backend keeps
its own subdirectory (``jax/``, ``numba/``).  Unset or empty: nothing is cached on disk (the
default for a library user who imports a backend directly).
"""

from __future__ import annotations

import os
from pathlib import Path

CACHE_ENV = "ISOBENCH_CACHE_DIR"


def subdir(name: str) -> Path | None:
    """``<cache dir>/<name>`` (created), or None when no cache directory is set."""
    root = os.environ.get(CACHE_ENV)
    if not root:
        return None
    d = Path(root) / name
    d.mkdir(parents=True, exist_ok=True)
    return d
