"""Suites: which cases, methods, dtypes and knob sweeps a run crosses with the backends.

A knob sweep is a list of knob dicts; each becomes one timed configuration (one point on the
backend's time-versus-error curve).  A method needs no entry here: its sweep is derived from
its knobs (:func:`default_sweep`), so a method added to ``impls.methods.METHODS`` is benchmarked
without touching ``bench/``.  ``Suite.sweeps`` overrides the derived sweep for a method.
"""

from __future__ import annotations

import dataclasses
import math
import re

import numpy as np

#: knob names treated as tolerances (swept over decades, tightest used while other knobs sweep)
_TOL_NAME = re.compile(r"(tol|eps|epsilon)$")  # tol, xtol, atol, rtol, f_tol, eps…
#: integer knobs that are not budgets (never swept by default)
_NOT_BUDGET = re.compile(r"seed|behaviou?r|mode|index|axis", re.I)


@dataclasses.dataclass(frozen=True)
class Suite:
    """name; case glob(s) and required tags; dtypes; ``sweeps`` (method → knob dicts) overriding
    the derived sweep; ``methods`` (None: every method in ``METHODS``); ``level`` passed to
    :func:`default_sweep` ("quick" or "full")."""

    name: str
    case_pattern: str
    dtypes: tuple[str, ...]
    sweeps: dict[str, list[dict]]
    case_tags: tuple[str, ...] = ()
    methods: tuple[str, ...] | None = None
    level: str = "quick"
    min_time_s: float = 0.2  # timed seconds per configuration (CLI --min-time overrides)

    def sweep_for(self, spec) -> list[dict]:
        if spec.name in self.sweeps:
            return [dict(k) for k in self.sweeps[spec.name]]
        return default_sweep(spec, self.level)


def _is_tolerance(knob) -> bool:
    return knob.kind is float and bool(_TOL_NAME.search(knob.name))


def _int_values(knob, level: str) -> list[int]:
    """Geometric values of an integer budget (steps, iterations, samples) up to its default
    (quick) or 4× its default (full), at least ``max(low, 1)``; the default is always included."""
    lo = max(int(knob.low), 1)
    hi = max(int(knob.default), lo) * (1 if level == "quick" else 4)
    n = 3 if level == "quick" else 7
    # rounded to powers of two so sweeps read well and repeat across methods
    vals = {int(2 ** round(math.log2(v))) for v in np.geomspace(max(lo, 2) if hi > 2 else lo, hi, n)}
    vals |= {int(knob.default)}
    return sorted(v for v in vals if v >= lo)


def _tol_values(knob, level: str) -> list[float]:
    ks = (4, 8, 12) if level == "quick" else range(2, 14)  # quick: the report's error targets
    return [10.0 ** -k for k in ks if 10.0 ** -k >= knob.low]


def default_sweep(spec, level: str = "quick") -> list[dict]:
    """One-at-a-time sweep over a method's accuracy knobs, derived from its :class:`Knob` list.

    * a knob may carry its own ``sweep`` (a tuple of values, optional attribute): used as is;
    * a float knob named like a tolerance (``tol``, ``xtol``, ``*_tol``, ``eps``): 1e-4, 1e-8, 1e-12 (quick:
      the report's error targets) or every decade 1e-2 … 1e-13 (full), the others at defaults;
    * an integer knob that is a budget (steps, iterations, samples — not a seed or a mode):
      3 (quick) or 7 (full) geometric
      values, rounded to powers of two, up to its default (quick) or 4× it (full), with every
      tolerance at its tightest swept value so the budget is what limits the error (a
      convergence curve in the budget);
    * other knobs (sharpness, band width, relaxation…) stay at their defaults unless they carry
      ``sweep``.
    Knob dicts are complete (every knob named) and unique, in a stable order.
    """
    knobs = list(spec.knobs)
    base = {k.name: k.default for k in knobs}
    tight = {}
    for k in knobs:
        if getattr(k, "sweep", None) is None and _is_tolerance(k):
            vals = _tol_values(k, level)
            if vals:
                tight[k.name] = min(vals)
    out: list[dict] = []
    for k in knobs:
        explicit = getattr(k, "sweep", None)
        if explicit is not None:
            out += [{**base, k.name: v} for v in explicit]
        elif _is_tolerance(k):
            out += [{**base, k.name: v} for v in _tol_values(k, level)]
        elif k.kind is int and not _NOT_BUDGET.search(k.name):
            out += [{**base, **tight, k.name: v} for v in _int_values(k, level)]
    if not out:
        out = [dict(base)]
    seen, unique = set(), []
    for kd in out:
        key = tuple(sorted((n, float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else str(v))
                           for n, v in kd.items()))
        if key not in seen:
            seen.add(key)
            unique.append(kd)
    return unique


SUITES = {
    # quick: CI and the README's first command, < 2 min on 2 cores: cases tagged "quick", float64,
    # 3-point sweeps, 0.05 s of timing per configuration.
    "quick": Suite(name="quick", case_pattern="*", case_tags=("quick",), dtypes=("float64",), sweeps={}, level="quick",
                   min_time_s=0.05),
    # full: every case, float64 and float32, the long sweeps, 0.1 s of timing per configuration.
    "full": Suite(name="full", case_pattern="*", dtypes=("float64", "float32"), sweeps={}, level="full",
                  min_time_s=0.1),
}


def get_suite(name: str) -> Suite:
    try:
        return SUITES[name]
    except KeyError:
        raise ValueError(f"unknown suite {name!r}; choose one of {sorted(SUITES)} (--suite)") from None

