"""Where the backends keep what they compile between runs.

The bench commands choose one cache directory (``--cache-dir``, default
``$XDG_CACHE_HOME/isobench``; ``--no-cache``: none) and hand it to the backends in the
environment variable :data:`CACHE_ENV`, set before any backend is imported; each backend keeps
its own subdirectory (``jax/``, ``numba/``).  Unset or empty: nothing is cached on disk (the
default for a library user who imports a backend directly).
"""

from __future__ import annotations

import functools
import hashlib
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


@functools.lru_cache(maxsize=None)
def source_digest(*packages: str) -> str:
    """SHA-256 over the relative paths and contents of every ``.py`` file of ``packages`` (top-level
    package names, e.g. ``"impls", "reference"``): what a cached answer or kernel computed by their
    code is also a function of, so that an edit of that code makes it a miss."""
    import importlib

    h = hashlib.sha256()
    for name in packages:
        for root in importlib.import_module(name).__path__:
            base = Path(root)
            for path in sorted(base.rglob("*.py")):
                h.update(f"{name}/{path.relative_to(base).as_posix()}\0".encode())
                h.update(path.read_bytes())
    return h.hexdigest()


def lock_numba_cache(dispatcher) -> None:
    """Keep ``dispatcher``'s compiled code on disk (what ``Dispatcher.enable_caching`` does) through
    :func:`_locked_function_cache`: safe when several processes compile it at once."""
    dispatcher._cache = _locked_function_cache()(dispatcher.py_func)


@functools.lru_cache(maxsize=None)
def _locked_function_cache():
    """numba's ``FunctionCache`` with each load and save under an exclusive lock on a file beside
    the function's cache index, and a loaded entry used only if it was compiled for the signature
    asked for.

    Why: numba's index is a read-modify-write without a lock (``IndexDataCacheFile.save``, numba
    0.68; numba issue #10128).  Two processes that compile different signatures of one function at
    once both read the index, both pick the first free data file, and the last index write and the
    last data write can come from different processes: the index then maps one signature to the
    other's machine code, and every later process that loads it runs that code on arguments of
    another type.  Reproduced with two processes (int64 and float64 arrays of one cached function,
    pauses put between numba's index read and its writes): the int64 call, loaded from disk,
    returned 4.45e-322 instead of 90.  The test suite and the quick run it starts share one cache
    directory, so this is the harness's own case.  The lock is the ``filelock`` package's (a
    well-kept cross-platform file lock); the signature check costs a tuple comparison.
    """
    from filelock import FileLock
    from numba.core import sigutils
    from numba.core.caching import FunctionCache

    class LockedFunctionCache(FunctionCache):
        def _lock(self) -> FileLock:
            self._impl.locator.ensure_cache_path()
            return FileLock(self._cache_file._index_path + ".lock")

        def load_overload(self, sig, target_context):
            with self._lock():
                cres = super().load_overload(sig, target_context)
                if cres is None or tuple(cres.signature.args) == tuple(sigutils.normalize_signature(sig)[0]):
                    return cres
                # another signature's code under this one's key: forget the key (so that the
                # fresh compile is saved to a data file of its own, not over the other's) and
                # compile afresh
                index = self._cache_file._load_index()
                index.pop(self._index_key(sig, target_context.codegen()), None)
                self._cache_file._save_index(index)
                return None

        def save_overload(self, sig, data):
            with self._lock():
                super().save_overload(sig, data)

    return LockedFunctionCache
