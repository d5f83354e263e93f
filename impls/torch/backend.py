"""torch backend: ``torch:cpu``, ``torch:cuda`` or ``torch:cuda:N``; eager execution."""

from __future__ import annotations

import array_api_compat.torch as xp_torch
import numpy as np
import torch

from ..base import ArrayBackend
from ..protocol import Capabilities
from . import gradients, param_grad, rendering, tracing


def _devices() -> tuple[str, ...]:
    devs = ["cpu"]
    if torch.cuda.is_available():
        devs.append("cuda")
        devs.extend(f"cuda:{i}" for i in range(torch.cuda.device_count()))
    return tuple(devs)


class TorchBackend(ArrayBackend):
    lib = "torch"
    xp = xp_torch
    _impl = {**tracing.IMPLS, **gradients.IMPLS, **param_grad.IMPLS, **rendering.IMPLS}

    def __init__(self, device: str = "cpu"):
        self.capabilities = Capabilities(
            dtypes=("float64", "float32"),
            devices=_devices(),
            autodiff="both",
            jit=False,
            notes=("eager; torch.compile is not used for timing",
                   "active-set loops (one host sync per iteration); dφ/dt by torch.func.jvp, ∇φ and the Hessian by "
                   "double backward, θ-Jacobians by torch.func.jacfwd",
                   "on a loaded 2-core machine torch's intra-op thread pool oversubscribes: set torch.set_num_threads(1) "
                   "(or OMP_NUM_THREADS=1) for timings — measured 40× slower otherwise"),
        )
        super().__init__(device)
        self.torch_device = torch.device(device)

    def asarray(self, a, dtype):
        return torch.as_tensor(np.asarray(a), dtype=getattr(torch, dtype), device=self.torch_device)

    def to_numpy(self, a):
        return a.detach().cpu().numpy()

    def synchronize(self, out=None):
        if self.torch_device.type == "cuda":
            torch.cuda.synchronize(self.torch_device)

    def versions(self):
        return {"torch": torch.__version__, "torch_threads": str(torch.get_num_threads())}
