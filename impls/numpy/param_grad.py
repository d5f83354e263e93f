"""dt/dθ on numpy: the shared formulas of :mod:`impls.core.param_grad` with central differences
in place of autodiff (∂φ/∂θ, the IDR trick and the unrolled tracer are differentiated by
central differences in θ, h_i = ε^{1/3}·max(1, |θ_i|))."""

from __future__ import annotations

import numpy as np

from ..core import param_grad
from . import gradients, tracing


def theta_jacobian(backend, fun, theta):
    return param_grad.central_jacobian(np, fun, np.asarray(theta, np.float64), lambda a: a.astype(theta.dtype))


IMPLS = param_grad.make_impls(gradients.grad_hess, theta_jacobian, tracing.solve, tracing.ray_eval)
