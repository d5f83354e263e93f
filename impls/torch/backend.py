"""torch backend: ``torch:cpu``, ``torch:cuda`` or ``torch:cuda:N``; eager execution."""

from __future__ import annotations

import math

import array_api_compat.torch as xp_torch
import numpy as np
import torch

from ..base import ArrayBackend
from ..core.driver import CompactingSettings
from ..protocol import Capabilities
from . import derivatives, driver


def _devices() -> tuple[str, ...]:
    devs = ["cpu"]
    if torch.cuda.is_available():
        devs.append("cuda")
        devs.extend(f"cuda:{i}" for i in range(torch.cuda.device_count()))
    return tuple(devs)


def _scalars_cached(kernel, general):
    """``kernel(x1, x2)`` with a Python scalar operand as :func:`_scalar_as_tensor` gives it;
    ``general(x1, x2)`` (array_api_compat's) where that does not apply."""

    def binary(x1, x2, /):
        a, b = _scalar_as_tensor(x1, x2), _scalar_as_tensor(x2, x1)
        if a is not None and b is not None:
            return kernel(a, b)
        return general(x1, x2)

    binary.__name__ = general.__name__
    return binary


class _FastTorchNamespace:
    """array_api_compat's torch namespace with torch's own kernels for the few functions that the
    root finders call on every step: in the straggler steps, on few rays, per-call overhead is
    the cost, and on 2^16 rays torch's ``isfinite`` kernel is the slow one.

    Each keeps the array-API meaning for the arguments isobench passes and falls back to
    array_api_compat otherwise: ``where`` without array_api_compat's dtype reconciliation (the
    root finders pass matching dtypes); ``clip`` with scalar bounds as ``clamp``; ``isfinite``
    as x − x == 0 (finite x gives +0, ±inf and NaN give NaN; one fused elementwise kernel
    instead of torch's two-pass one); ``take_along_axis`` without array_api_compat's
    negative-index fix-up (the root finders' indices are never negative); ``maximum`` and
    ``minimum`` with a Python scalar as a cached 0-d tensor (:func:`_scalar_as_tensor`), the
    operands array_api_compat would pass, so the results are the same to the sign of zero."""

    def __getattr__(self, name):
        return getattr(xp_torch, name)

    @staticmethod
    def where(condition, x1, x2, /):
        t1, t2 = isinstance(x1, torch.Tensor), isinstance(x2, torch.Tensor)
        if (t1 and t2 and x1.dtype == x2.dtype) or (t1 and _weak_scalar_of(x2, x1)) or (t2 and _weak_scalar_of(x1, x2)):
            return torch.where(condition, x1, x2)  # the tensor's dtype, as the array API's rules give
        return xp_torch.where(condition, x1, x2)

    @staticmethod
    def clip(x, /, min=None, max=None):
        if x.is_floating_point() and isinstance(min, float) and isinstance(max, float) and min <= max:
            return torch.clamp(x, min, max)
        return xp_torch.clip(x, min, max)

    @staticmethod
    def isfinite(x, /):
        if x.is_floating_point():
            return (x - x) == 0
        return xp_torch.isfinite(x)

    @staticmethod
    def take_along_axis(x, indices, /, *, axis=-1):
        return torch.take_along_dim(x, indices, dim=axis)

    maximum = staticmethod(_scalars_cached(torch.maximum, xp_torch.maximum))
    minimum = staticmethod(_scalars_cached(torch.minimum, xp_torch.minimum))


#: 0-d tensors of the Python scalars the root finders pass to maximum/minimum, by (value, sign,
#: dtype, device): array_api_compat makes a fresh one on every call (torch.asarray and its dtype
#: rules cost several times the operation itself on a few hundred rays); never written to
_SCALARS: dict = {}


def _scalar_as_tensor(v, other):
    """``v`` where it is a tensor of ``other``'s dtype (or ``other`` is not a tensor: checked on the
    other side); a Python float or int as the 0-d tensor of floating ``other``'s dtype and device,
    as array_api_compat converts it (the tensor's dtype, by the array API's rules); None where
    array_api_compat's general path is needed (other dtypes, NaN, a full cache)."""
    if isinstance(v, torch.Tensor):
        return v if not isinstance(other, torch.Tensor) or v.dtype == other.dtype else None
    if not (isinstance(other, torch.Tensor) and _weak_scalar_of(v, other) and other.is_floating_point()) or v != v:
        return None
    key = (float(v), math.copysign(1.0, v), other.dtype, other.device)
    t = _SCALARS.get(key)
    if t is None:
        if len(_SCALARS) >= 1024:
            return None
        t = _SCALARS[key] = torch.asarray(v, dtype=other.dtype, device=other.device)
    return t


def _weak_scalar_of(v, t) -> bool:
    """A Python scalar that keeps tensor ``t``'s dtype in a binary operation: a float with a
    floating tensor, an int with a floating or integer (not bool) tensor."""
    if isinstance(v, float):
        return t.is_floating_point()
    return isinstance(v, int) and not isinstance(v, bool) and t.dtype != torch.bool and not t.is_complex()


xp_fast = _FastTorchNamespace()


class TorchBackend(ArrayBackend):
    lib = "torch"
    xp = xp_fast
    settings = CompactingSettings()

    def __init__(self, device: str = "cpu", settings: CompactingSettings | None = None):
        self.capabilities = Capabilities(
            dtypes=("float64", "float32"),
            devices=_devices(),
            autodiff="both",
            jit=False,
            notes=("eager; torch.compile is not used for timing",
                   "active-set loops (one host sync per iteration); on the CPU the loop's step arithmetic runs on numpy "
                   "views of the same memory and φ in torch (impls.torch.driver: float64 bit for bit the same, float32 "
                   "to rounding); dφ/dt and ∇φ by one backward pass, the Hessian by "
                   "double backward, θ-Jacobians by torch.func.jacfwd",
                   "namespace: array_api_compat.torch with torch's own where, clip, isfinite and take_along_axis "
                   "(impls.torch.backend.xp_fast; per-call overhead)",
                   "on a machine whose cores are busy, torch's OpenMP intra-op threads spin at every parallel region's "
                   "barrier: set OMP_WAIT_POLICY=PASSIVE and OMP_NUM_THREADS before torch is imported (the bench "
                   "commands do, bench.run.environment.configure_threads): a spinning thread holds the core its partner needs"),
        )
        super().__init__(device, settings)
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

    @staticmethod
    def stop_gradient(a):
        return a.detach()

    def compile(self, fn, *example_args):
        """Nothing to compile (eager); the call runs under ``torch.no_grad()``: ``prepare``'s outputs
        go to numpy (``Prepared.result``), so no autograd graph is needed, and where grad mode was
        on (torch's default) the dφ/dt of ``dt_finite_diff``'s Newton re-solves kept theirs
        (``create_graph``, :func:`impls.torch.derivatives.ray_eval`), chained through the iterates
        (memory growing with the rays: CHANGELOG).  Differentiating a method's output in θ stays
        with its function called directly (e.g. ``render_surface``)."""

        def run(*args):
            with torch.no_grad():
                return fn(*args)

        return run, None

    def ray_eval(self, scene, theta=None):
        return derivatives.ray_eval(self.xp, scene, theta)

    def grad_hess(self, scene, x, hess, theta=None):
        return derivatives.grad_hess(self.xp, scene, x, hess, theta)

    def theta_jacobian(self, fun, theta):
        return derivatives.theta_jacobian(fun, theta)

    def run_loop(self, alg, o, d, ev):
        return driver.run_loop(self.xp, alg, o, d, ev, self.settings)
