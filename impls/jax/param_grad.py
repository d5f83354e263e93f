"""dt/dθ in jax: :mod:`impls.core.param_grad` with ``jax.jacfwd`` in θ (P tangents, one φ call)."""

from __future__ import annotations

import jax
from jax import lax

from ..core import param_grad
from . import gradients, tracing


def theta_jacobian(backend, fun, theta):
    return jax.jacfwd(fun)(theta), 1


IMPLS = param_grad.make_impls(gradients.grad_hess, theta_jacobian, tracing.solve, tracing.ray_eval,
                               fori_loop=lax.fori_loop)
