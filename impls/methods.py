"""The method catalog: names, knobs (the accuracy dials bench sweeps), and scene requirements.

One table shared by every backend, by the planner (which skips a method whose requirement the
scene does not meet, with the reason) and by the conformance tests.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any


@dataclasses.dataclass(frozen=True)
class Knob:
    name: str
    default: Any
    kind: type
    low: float  # inclusive lower bound
    doc: str

    def check(self, method: str, value: Any) -> Any:
        try:
            v = self.kind(value)
        except (TypeError, ValueError):
            raise ValueError(f"{method}: knob {self.name}={value!r} must be {self.kind.__name__} ({self.doc})") from None
        if self.kind is int and v != value:
            raise ValueError(f"{method}: knob {self.name}={value!r} must be an integer ({self.doc})")
        if not (math.isfinite(v) and v >= self.low):
            raise ValueError(f"{method}: knob {self.name}={value!r} must be finite and ≥ {self.low} ({self.doc})")
        return v


@dataclasses.dataclass(frozen=True)
class MethodSpec:
    """A method's contract.

    family:   ``root`` (finds t), ``gradient`` (normals/curvature at given hits), ``param_grad``
              (dt/dθ at given hits), ``render`` (colour per ray); bench measures each family's
              error against the matching reference answer.
    requires: :class:`reference.SceneInfo` fields that must be truthy for the method to apply
              (e.g. ``lipschitz`` for sphere tracing).
    needs_t_hit: the method evaluates at given per-ray depths (``prepare(..., t_hit=...)``).
    outputs:  names of the extra per-ray outputs in :attr:`RayResult.outputs`.
    """

    name: str
    family: str
    knobs: tuple[Knob, ...]
    requires: tuple[str, ...]
    description: str
    needs_t_hit: bool = False
    outputs: tuple[str, ...] = ()

    def skip_reason(self, scene) -> str | None:
        info = scene.info
        missing = [r for r in self.requires if not getattr(info, r)]
        if missing:
            return f"{self.name} needs a scene with {', '.join(missing)}; {type(scene).__name__} states none"
        return None

    def validate(self, knobs: dict[str, Any]) -> dict[str, Any]:
        names = {k.name for k in self.knobs}
        unknown = set(knobs) - names
        if unknown:
            raise ValueError(f"{self.name}: unknown knob(s) {sorted(unknown)}; valid knobs are {sorted(names)}")
        return {k.name: k.check(self.name, knobs.get(k.name, k.default)) for k in self.knobs}


METHODS: dict[str, MethodSpec] = {
    m.name: m
    for m in [
        MethodSpec(
            name="sphere_trace",
            family="root",
            knobs=(
                Knob("tol", 1e-10, float, 0.0, "stop when |φ(o + t d)| ≤ tol"),
                Knob("max_steps", 512, int, 1, "step budget per ray"),
            ),
            requires=("lipschitz",),
            description="Hart's sphere tracing t ← t + |φ|/L from t_min until |φ| ≤ tol "
            "(lecture: 'Sphere Tracing'); L is the scene's Lipschitz bound",
        ),
    ]
}


def get_method(name: str) -> MethodSpec:
    try:
        return METHODS[name]
    except KeyError:
        raise ValueError(f"unknown method {name!r}; known methods: {sorted(METHODS)}") from None
