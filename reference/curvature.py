"""Curvature conventions and helpers — the one place they are defined.

Convention (used by every ``curvatures_exact``): principal curvatures κ1 ≥ κ2 of the level set
φ = 0, *positive where the surface bends away from its outward normal* n = ∇φ/|∇φ| (a sphere of
radius r has κ1 = κ2 = +1/r; the inner equator of a torus has κ2 = −1/(R − r)).

* mean curvature H = (κ1 + κ2)/2 (differential-geometry convention, do Carmo §3-2);
* curvature sum κ1 + κ2 = ∇·(∇φ/|∇φ|), which equals Δφ for an exact SDF (|∇φ| = 1): this is
  what the lecture calls "mean curvature" (slide "Properties - Mean Curvature");
* Gaussian curvature K = κ1 κ2.

For an implicit surface the principal curvatures are the eigenvalues of the shape operator
P H_φ P / |∇φ| restricted to the tangent plane, P = I − n nᵀ, H_φ the Hessian (Goldman,
"Curvature formulas for implicit curves and surfaces", CAGD 22, 2005, eq. 4.1 up to the
sign convention above).
"""

from __future__ import annotations

import numpy as np


def mean_curvature(k1, k2):
    """H = (κ1 + κ2)/2."""
    return (np.asarray(k1) + np.asarray(k2)) / 2


def curvature_sum(k1, k2):
    """κ1 + κ2 = div(∇φ/|∇φ|) (= Δφ for an exact SDF): the lecture's 'mean curvature'."""
    return np.asarray(k1) + np.asarray(k2)


def gaussian_curvature(k1, k2):
    """K = κ1 κ2."""
    return np.asarray(k1) * np.asarray(k2)


def tangent_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the plane orthogonal to each unit row of ``n``."""
    n = np.asarray(n, np.float64)
    e = np.eye(3)[np.argmin(np.abs(n), axis=1)]  # the axis least aligned with n: well conditioned
    t1 = e - np.einsum("ij,ij->i", e, n)[:, None] * n
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    return t1, np.cross(n, t1)


def principal_from_hessian(grad: np.ndarray, hess: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(κ1, κ2), κ1 ≥ κ2, from ∇φ (n, 3) and the Hessian (n, 3, 3) at surface points.

    The shape operator on the tangent basis (t1, t2) is the symmetric 2×2 matrix
    B_ij = t_iᵀ H_φ t_j / |∇φ|; its eigenvalues, in closed form m ± √(((B11 − B22)/2)² + B12²),
    are the principal curvatures."""
    grad = np.asarray(grad, np.float64)
    g = np.linalg.norm(grad, axis=1)
    t1, t2 = tangent_basis(grad / g[:, None])
    b11 = np.einsum("ni,nij,nj->n", t1, hess, t1) / g
    b22 = np.einsum("ni,nij,nj->n", t2, hess, t2) / g
    b12 = np.einsum("ni,nij,nj->n", t1, hess, t2) / g
    m = (b11 + b22) / 2
    r = np.hypot((b11 - b22) / 2, b12)
    return m + r, m - r
