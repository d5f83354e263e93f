"""A user's plug-in backend that kills its own process on one configuration, as a segfault or an
abort in a native library would: it wraps numpy, and where the method, dtype, scene kind and knob
match the environment (``CRASH_METHOD``, ``CRASH_DTYPE``, ``CRASH_KIND``, ``CRASH_KNOB`` as
``name=value``; each optional), its ``run`` raises SIGSEGV (``CRASH_HOW=exit``: ``os._exit(3)``; ``CRASH_HOW=exit0``:
``os._exit(0)``, an exit that looks like success; ``CRASH_HOW=hang``: it blocks SIGALRM,
the time limit's signal, and sleeps for an hour, as a kernel that never returns to Python would).
Used by tests/test_crash_isolation.py through ``--backend tests.crash_backend:CrashBackend``."""

from __future__ import annotations

import dataclasses
import os
import signal
import time

from tests.plugin_backend import PluginBackend


def _matches(method, scene, dtype, knobs) -> bool:
    env = os.environ
    if env.get("CRASH_METHOD", method) != method or env.get("CRASH_DTYPE", dtype) != dtype:
        return False
    if env.get("CRASH_KIND", scene.kind) != scene.kind:
        return False
    if "CRASH_KNOB" in env:
        name, value = env["CRASH_KNOB"].split("=")
        return name in knobs and float(knobs[name]) == float(value)
    return True


class CrashBackend(PluginBackend):
    """tests/plugin_backend.py's numpy wrapper, under its own id, crashing where the environment says."""

    lib = "crashy"

    def __init__(self, device: str = "cpu"):
        super().__init__(device)
        self.id = "crashy"

    def prepare(self, method, scene, origins, directions, **kwargs):
        prep = super().prepare(method, scene, origins, directions, **kwargs)
        knobs = {k: v for k, v in kwargs.items() if k not in ("dtype", "t_min", "t_max", "t_hit", "color")}
        if not _matches(method, scene, kwargs.get("dtype", "float64"), knobs):
            return prep

        def run():
            how = os.environ.get("CRASH_HOW")
            if how in ("exit", "exit0"):
                os._exit(3 if how == "exit" else 0)
            if how == "hang":  # as native code that never returns: the time limit's SIGALRM is never seen
                signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGALRM})
                time.sleep(3600)
            os.kill(os.getpid(), signal.SIGSEGV)

        return dataclasses.replace(prep, run=run)

    def versions(self):
        return {"crashy": "0.1"}
