"""numpy backend: CPU only, eager, no autodiff."""

from __future__ import annotations

import numpy as np

from ..base import HostArrayBackend
from ..core.driver import CompactingSettings
from ..protocol import Capabilities
from . import derivatives, driver


class NumpyBackend(HostArrayBackend):
    lib = "numpy"
    xp = np
    capabilities = Capabilities(
        dtypes=("float64", "float32"),
        devices=("cpu",),
        autodiff=None,
        jit=False,
        notes=("no autodiff (scenes provide no analytic gradient yet): every derivative is a central difference — "
               "dφ/dt and ∇φ with h = ε^(1/3)·max(1,|·|) (≈1e-10 relative), the Hessian with h = ε^(1/4)·max(1,|x|) "
               "(≈1e-8), ∂φ/∂θ and the IDR Jacobian in θ with h = ε^(1/3)·max(1,|θ_i|); the unrolled tracer's "
               "dt/dθ by the chain rule through every step (impls.core.param_grad.unrolled_chain_rule)",
               "active-set loops: only rays still iterating are evaluated; early-terminated volume rays are dropped"),
    )
    settings = CompactingSettings()
    stop_gradient = None  # no autodiff: render_surface shades at the root finder's hit

    def versions(self):
        return {"numpy": np.__version__}

    def ray_eval(self, scene, theta=None):
        return derivatives.ray_eval(scene, theta)

    def grad_hess(self, scene, x, hess, theta=None):
        return derivatives.grad_hess(scene, x, hess, theta)

    def theta_jacobian(self, fun, theta):
        return derivatives.theta_jacobian(fun, theta)

    def run_loop(self, alg, o, d, ev):
        return driver.run_loop(alg, o, d, ev, self.settings)
