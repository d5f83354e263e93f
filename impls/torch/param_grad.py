"""dt/dθ on torch: :mod:`impls.core.param_grad` with forward-mode Jacobians in θ
(``torch.func.jacfwd``: P tangents, vectorised; one φ call per point)."""

from __future__ import annotations

import torch

from ..core import param_grad
from . import gradients, tracing


def theta_jacobian(backend, fun, theta):
    with torch.no_grad():
        return torch.func.jacfwd(fun)(theta), 1


IMPLS = param_grad.make_impls(gradients.grad_hess, theta_jacobian, tracing.solve, tracing.ray_eval)
