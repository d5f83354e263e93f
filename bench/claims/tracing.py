"""Sphere tracing exactly as the lecture writes it.

The tracer is the object of study of claims 4c and 5 (its step rule is varied), so it is written
here rather than taken from a backend: t ← t + φ(o + t d)/L (signed step, the lecture's
"t = t + f(x_{n−1})" with L = 1), until |φ| ≤ ε.  The backends' ``sphere_trace`` (``impls/``)
steps |φ|/L and is checked against the reference by the conformance suite instead.
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass
class TraceResult:
    t: np.ndarray  #: final depth (inf: left through t_max)
    converged: np.ndarray  #: |φ| ≤ tol reached
    t_furthest: np.ndarray  #: the largest depth any iterate reached (to detect passing through)
    iterations: np.ndarray


def sphere_trace_signed(f, o, d, *, lipschitz: float = 1.0, tol: float = 1e-10, max_steps: int = 2000,
                        t_min: float = 0.0, t_max: float = 10.0, abs_step: bool = False) -> TraceResult:
    """Vectorised sphere tracing t ← t + φ/L on rays o + t d (numpy float64).

    ``abs_step=True`` steps |φ|/L instead (a ray starting inside marches forward to its exit); on a ray
    that starts outside and never overshoots the two rules take identical steps."""
    if not (lipschitz > 0):
        raise ValueError(f"lipschitz must be > 0, got {lipschitz!r}")
    n = o.shape[0]
    t = np.full(n, float(t_min))
    far = t.copy()
    conv = np.zeros(n, bool)
    active = np.ones(n, bool)
    iters = np.zeros(n, np.int64)
    for _ in range(max_steps):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        fv = f(o[idx] + t[idx, None] * d[idx])
        done = np.abs(fv) <= tol
        conv[idx[done]] = True
        active[idx[done]] = False
        go = idx[~done]
        step = np.abs(fv[~done]) if abs_step else fv[~done]
        t[go] += step / lipschitz
        iters[go] += 1
        far[go] = np.maximum(far[go], t[go])
        out = go[(t[go] > t_max) | (t[go] < t_min - t_max) | ~np.isfinite(t[go])]
        t[out] = np.inf
        active[out] = False
    return TraceResult(t=t, converged=conv, t_furthest=far, iterations=iters)


def camera_rays(n_side: int, eye=(0.3, 0.4, 3.5), fov_deg: float = 45.0):
    """A pinhole grid of rays looking at the origin (reference.rays.pinhole)."""
    from reference.rays import pinhole

    return pinhole(eye=eye, look_at=(0.0, 0.0, 0.0), fov_deg=fov_deg, width=n_side, height=n_side)
