"""Suites: which cases, methods, dtypes and knob sweeps a run crosses with the backends.

A knob sweep is a list of knob dicts; each becomes one timed configuration (one point on the
backend's time-versus-error curve).
"""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class Suite:
    name: str
    case_pattern: str
    dtypes: tuple[str, ...]
    sweeps: dict[str, list[dict]]  # method -> knob dicts


def _sphere_trace_sweep(tols, budgets) -> list[dict]:
    # A tolerance sweep at a generous budget, then a budget sweep at a tight tolerance:
    # the two accuracy dials of sphere tracing.
    return [{"tol": t, "max_steps": 512} for t in tols] + [{"tol": 1e-12, "max_steps": b} for b in budgets]


SUITES = {
    "quick": Suite(
        name="quick",
        case_pattern="*",
        dtypes=("float64",),
        sweeps={"sphere_trace": _sphere_trace_sweep([1e-2, 1e-4, 1e-6, 1e-8, 1e-10, 1e-12], [4, 16, 64])},
    ),
    "full": Suite(
        name="full",
        case_pattern="*",
        dtypes=("float64", "float32"),
        sweeps={"sphere_trace": _sphere_trace_sweep([10.0 ** -k for k in range(1, 14)], [2, 4, 8, 16, 32, 64, 128, 256])},
    ),
}


def get_suite(name: str) -> Suite:
    try:
        return SUITES[name]
    except KeyError:
        raise ValueError(f"unknown suite {name!r}; choose one of {sorted(SUITES)}") from None
