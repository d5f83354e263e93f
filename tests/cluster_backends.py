"""Plug-in backends that misbehave on purpose, for tests/test_cluster.py: they wrap the numpy
backend and kill their own worker process (SIGKILL, as a segfault or the OOM killer would) or
run slowly.  Only ever run them on a cluster: killing is what they are for.

``ISOBENCH_TEST_MARKERS`` names a directory: ``KillOnce`` kills the first process that prepares a
configuration and leaves a marker file there, so the rerun elsewhere runs normally."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

from impls.numpy.backend import NumpyBackend


class _Wrapped:
    lib = "numpy-test"

    def __init__(self, device: str = "cpu"):
        self._inner = NumpyBackend(device)
        self.device = device
        self.id = type(self).__name__
        self.capabilities = self._inner.capabilities

    def methods(self):
        return self._inner.methods()

    def prepare(self, method, scene, origins, directions, **kwargs):
        return self._inner.prepare(method, scene, origins, directions, **kwargs)

    def synchronize(self, out=None):
        return None

    def versions(self):
        return self._inner.versions()


def _die() -> None:
    os.kill(os.getpid(), signal.SIGKILL)


class KillOnce(_Wrapped):
    """Kills the process of the first configuration it prepares (anywhere), then behaves."""

    def prepare(self, method, scene, origins, directions, **kwargs):
        marker = Path(os.environ["ISOBENCH_TEST_MARKERS"]) / "killed-once"
        try:
            os.close(os.open(marker, os.O_WRONLY | os.O_CREAT | os.O_EXCL))
        except FileExistsError:
            return super().prepare(method, scene, origins, directions, **kwargs)
        _die()


class KillAlways(_Wrapped):
    """Kills its process whenever it prepares a configuration with ``tol`` = 1e-12 (one
    configuration of a sphere_trace sweep); behaves otherwise."""

    def prepare(self, method, scene, origins, directions, **kwargs):
        if kwargs.get("tol") == 1e-12:
            _die()
        return super().prepare(method, scene, origins, directions, **kwargs)


class Slow(_Wrapped):
    """Sleeps ``ISOBENCH_TEST_SLOW_S`` seconds (default 0.4) in every prepare: a run long enough
    to be killed in the middle."""

    def prepare(self, method, scene, origins, directions, **kwargs):
        time.sleep(float(os.environ.get("ISOBENCH_TEST_SLOW_S", "0.4")))
        return super().prepare(method, scene, origins, directions, **kwargs)
