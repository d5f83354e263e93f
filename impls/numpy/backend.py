"""numpy backend: CPU only, eager, no autodiff."""

from __future__ import annotations

import numpy as np

from ..base import ArrayBackend
from ..protocol import Capabilities
from . import gradients, param_grad, rendering, tracing


class NumpyBackend(ArrayBackend):
    lib = "numpy"
    xp = np
    capabilities = Capabilities(
        dtypes=("float64", "float32"),
        devices=("cpu",),
        autodiff=None,
        jit=False,
        notes=("no autodiff: derivatives are analytic where the scene provides them, else central finite differences",),
    )
    _impl = {**tracing.IMPLS, **gradients.IMPLS, **param_grad.IMPLS, **rendering.IMPLS}

    def asarray(self, a, dtype):
        return np.ascontiguousarray(a, dtype=np.dtype(dtype))

    def to_numpy(self, a):
        return np.asarray(a)

    def versions(self):
        return {"numpy": np.__version__}
