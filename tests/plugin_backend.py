"""A minimal third-party backend, as a user would write it outside isobench: it wraps the numpy
backend under its own id and declares its own capabilities.  Nothing in isobench refers to it;
it is found by ``--backend tests.plugin_backend:PluginBackend`` or by an entry point in the
group ``isobench.backends``."""

from __future__ import annotations

import dataclasses

from impls.numpy.backend import NumpyBackend


class PluginBackend:
    lib = "npwrap"

    def __init__(self, device: str = "cpu"):
        self._inner = NumpyBackend(device)
        self.device = device
        self.id = "npwrap"
        self.capabilities = dataclasses.replace(self._inner.capabilities,
                                                notes=self._inner.capabilities.notes + ("plug-in wrapping numpy",))

    def methods(self):
        return self._inner.methods()

    def prepare(self, method, scene, origins, directions, **kwargs):
        return self._inner.prepare(method, scene, origins, directions, **kwargs)

    def synchronize(self, out=None):
        return None

    def versions(self):
        return {"npwrap": "0.1", **self._inner.versions()}
