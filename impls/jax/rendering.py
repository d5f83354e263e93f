"""Renderers on jax: ``impls.core.rendering`` bound to this backend's root finder;
``render_surface`` is differentiable through the hit
(masked blocks: early termination is reported, not realised)."""

from __future__ import annotations

import jax

from ..core import rendering
from . import gradients, tracing

IMPLS = rendering.make_impls(tracing.solve, compact=False, grad_hess=gradients.grad_hess,
                               stop_gradient=jax.lax.stop_gradient)
render_surface = IMPLS["render_surface"]  # differentiable in theta, o, d through the hit
