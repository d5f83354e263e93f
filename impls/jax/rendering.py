"""Renderers on jax: ``impls.core.rendering`` bound to this backend's root finder
(masked blocks: early termination is reported, not realised)."""

from __future__ import annotations

from ..core import rendering
from . import tracing

IMPLS = rendering.make_impls(tracing.solve, compact=False)
