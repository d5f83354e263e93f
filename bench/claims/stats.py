"""Small numerical helpers shared by the claim checks (rate fits, relative errors)."""

from __future__ import annotations

import numpy as np


def fit_power(x, y) -> tuple[float, float]:
    """Least-squares fit of log y = s log x + c over the finite, positive points; returns (s, c).

    Used for convergence rates: error ∝ x^s.  Raises ValueError when fewer than two usable points.
    """
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    ok = np.isfinite(x) & np.isfinite(y) & (x > 0) & (y > 0)
    if ok.sum() < 2:
        raise ValueError(f"fit_power needs ≥ 2 finite positive points, got {int(ok.sum())}")
    s, c = np.polyfit(np.log(x[ok]), np.log(y[ok]), 1)
    return float(s), float(c)


def rel_err(a, b, floor: float = 1e-300):
    """|a − b| / max(|b|, floor), elementwise (b is the truth)."""
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    return np.abs(a - b) / np.maximum(np.abs(b), floor)


def central_gradient(f, x, h: float = 1e-5):
    """∇f at points ``x`` (…, 3) by central differences, error O(h²) + O(ε/h)."""
    x = np.asarray(x, float)
    g = np.empty_like(x)
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        g[..., k] = (f(x + e) - f(x - e)) / (2 * h)
    return g


def central_laplacian(f, x, h: float = 1e-3):
    """Δf at points ``x`` (…, 3) by the 7-point stencil, error O(h²) + O(ε/h²)."""
    x = np.asarray(x, float)
    f0 = f(x)
    out = -6.0 * f0
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        out = out + f(x + e) + f(x - e)
    return out / h**2
