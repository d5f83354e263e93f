"""∇φ and the Hessian on numpy by central differences (numpy has no autodiff; scenes give no
analytic gradient), bound to the shared formulas of :mod:`impls.core.pointwise`."""

from __future__ import annotations

import numpy as np

from ..core import pointwise


def _steps(x, power):
    """Per-point step h = ε^power·max(1, |x|_∞) (scaled so it stays above rounding at large |x|)."""
    eps = np.finfo(x.dtype).eps
    return (eps**power * np.maximum(1.0, np.max(np.abs(x), axis=-1))).astype(x.dtype)


def grad_hess(backend, scene, x, hess, theta=None):
    """Central differences.  ∇φ: h = ε^{1/3}·max(1, |x|) (error O(h²) + O(ε/h) ≈ 1e-11 relative);
    H: h = ε^{1/4}·max(1, |x|), diagonal (φ(x+he_i) − 2φ(x) + φ(x−he_i))/h² and off-diagonal
    (φ(++) − φ(+−) − φ(−+) + φ(−−))/4h² (error ≈ 1e-8 relative).  Cost: 6 evaluations per
    point for ∇φ, 6 + 19 with H."""
    n = x.shape[0]
    eye = np.eye(3, dtype=x.dtype)
    h1 = _steps(x, 1 / 3)
    pts = [x[:, None, :] + h1[:, None, None] * eye, x[:, None, :] - h1[:, None, None] * eye]  # (n, 3, 3) each
    f = scene.value(np.concatenate(pts, axis=1), np, theta)  # (n, 6)
    g = (f[:, :3] - f[:, 3:]) / (2 * h1[:, None])
    if not hess:
        return g, None, 6
    h2 = _steps(x, 1 / 4)
    he = h2[:, None, None] * eye  # (n, 3, 3): row i = h e_i
    ij = [(0, 1), (0, 2), (1, 2)]
    cross = []
    for i, j in ij:
        for si, sj in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
            cross.append(x + si * he[:, i] + sj * he[:, j])
    pts = np.stack([x, *(x + he[:, i] for i in range(3)), *(x - he[:, i] for i in range(3)), *cross], axis=1)
    f = scene.value(pts, np, theta)  # (n, 19)
    H = np.empty((n, 3, 3), dtype=x.dtype)
    h2s = h2 * h2
    for i in range(3):
        H[:, i, i] = (f[:, 1 + i] - 2 * f[:, 0] + f[:, 4 + i]) / h2s
    for k, (i, j) in enumerate(ij):
        pp, pm, mp, mm = (f[:, 7 + 4 * k + m] for m in range(4))
        H[:, i, j] = H[:, j, i] = (pp - pm - mp + mm) / (4 * h2s)
    return g, H, 6 + 19


IMPLS = pointwise.make_impls(grad_hess)
