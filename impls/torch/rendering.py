"""Renderers on torch: ``impls.core.rendering`` bound to this backend's root finder;
``render_surface`` is differentiable through the hit
(terminated rays are dropped from later blocks)."""

from __future__ import annotations

from ..core import rendering
from . import gradients, tracing

IMPLS = rendering.make_impls(tracing.solve, compact=True, grad_hess=gradients.grad_hess,
                               stop_gradient=lambda a: a.detach())
render_surface = IMPLS["render_surface"]  # differentiable in theta, o, d through the hit
