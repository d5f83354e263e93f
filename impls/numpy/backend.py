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
        notes=("no autodiff (scenes provide no analytic gradient yet): every derivative is a central difference — "
               "dφ/dt and ∇φ with h = ε^(1/3)·max(1,|·|) (≈1e-10 relative), the Hessian with h = ε^(1/4)·max(1,|x|) "
               "(≈1e-8), ∂φ/∂θ and the IDR/unrolled Jacobians in θ with h = ε^(1/3)·max(1,|θ_i|)",
               "active-set loops: only rays still iterating are evaluated; early-terminated volume rays are dropped"),
    )
    _impl = {**tracing.IMPLS, **gradients.IMPLS, **param_grad.IMPLS, **rendering.IMPLS}

    def asarray(self, a, dtype):
        return np.ascontiguousarray(a, dtype=np.dtype(dtype))

    def to_numpy(self, a):
        return np.asarray(a)

    def versions(self):
        return {"numpy": np.__version__}
