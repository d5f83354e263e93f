"""Renderers on numpy: ``impls.core.rendering`` bound to this backend's root finder
(terminated rays are dropped from later blocks)."""

from __future__ import annotations

from ..core import rendering
from . import tracing

IMPLS = rendering.make_impls(tracing.solve, compact=True)
render_surface = IMPLS["render_surface"]  # no autodiff: ρ at the root finder's hit
