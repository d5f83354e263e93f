"""Scenes and exact geometry shared by several claims (one place, no claim imports another's
private helpers): the torus and ellipsoid the claims use, points on their surfaces from a
parametrisation (not from φ), exact normals and closest points, the closed-form hit-depth
derivative of the unit sphere, and the hit-depth derivative of any scene by eq. 8 and by the
forward trick (claims 7 and 11).
"""

from __future__ import annotations

import numpy as np

from reference import Torus
from reference.arrays import unit

TORUS = (1.0, 0.4)  # R, r of the torus used by claims 2, 3 and 12
AXES = (1.0, 0.7, 0.5)  # semi-axes of the ellipsoid


def torus():
    return Torus(major=TORUS[0], minor=TORUS[1])


def surface_points(shape_name: str, n: int, rng):
    """Points on the zero set of the named family, from a parametrisation (not from φ)."""
    u = rng.uniform(0, 2 * np.pi, n)
    v = rng.uniform(0.15, np.pi - 0.15, n)  # keep away from the poles of the parametrisation
    if shape_name == "torus":
        R, r = TORUS
        return np.stack([(R + r * np.cos(v * 2)) * np.cos(u), (R + r * np.cos(v * 2)) * np.sin(u), r * np.sin(v * 2)], -1)
    if shape_name == "ellipsoid":
        a = AXES
        return np.stack([a[0] * np.cos(u) * np.sin(v), a[1] * np.sin(u) * np.sin(v), a[2] * np.cos(v)], -1)
    return np.stack([np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v)], -1)  # unit sphere


def _ring_point(x):
    """The point of the torus's core circle (radius R in z = 0) nearest to x."""
    rho = np.hypot(x[..., 0], x[..., 1])
    return np.stack([TORUS[0] * x[..., 0] / rho, TORUS[0] * x[..., 1] / rho, np.zeros_like(rho)], -1)


def geometric_normal(fam: str, x):
    """Outward unit normal at surface points from the geometry alone: radial for the unit sphere, from the
    core circle for the torus, ∂x/∂u × ∂x/∂v of x = (a cos u sin v, b sin u sin v, c cos v) for the ellipsoid."""
    x = np.asarray(x, float)
    if fam == "torus":
        return unit(x - _ring_point(x))
    if fam == "ellipsoid":
        a = np.asarray(AXES)
        u = np.arctan2(x[..., 1] / a[1], x[..., 0] / a[0])
        v = np.arccos(np.clip(x[..., 2] / a[2], -1, 1))
        xu = np.stack([-a[0] * np.sin(u) * np.sin(v), a[1] * np.cos(u) * np.sin(v), 0 * u], -1)
        xv = np.stack([a[0] * np.cos(u) * np.cos(v), a[1] * np.sin(u) * np.cos(v), -a[2] * np.sin(v)], -1)
        n = unit(np.cross(xu, xv))
        return np.where(np.sum(n * x, -1, keepdims=True) < 0, -n, n)
    return unit(x)


def geometric_closest(fam: str, x):
    """Exact closest surface point (off the medial axis): radial projection onto the unit sphere; for the
    torus the core-circle point plus r times the unit vector towards x."""
    x = np.asarray(x, float)
    if fam == "torus":
        c = _ring_point(x)
        return c + TORUS[1] * unit(x - c)
    return unit(x)


def sphere_dt_truth(b, r=1.0):
    """Exact dt/dθ for θ = (centre x, y, z, radius) of a sphere of radius r at the origin, on the ray
    x = (b, 0, 3) + t (0, 0, −1), and |⟨n, d⟩| there: t* = 3 − √(r² − b²), so
    dt/dc = (−b/s, 0, −1) and dt/dr = −r/s with s = √(r² − b²); |⟨n, d⟩| = s/r."""
    s = np.sqrt((r - b) * (r + b))
    return np.stack([-b / s, np.zeros_like(b), -np.ones_like(b), -r / s], -1), s / r


def implicit_and_trick(scene, o, d, t):
    """dt/dθ at the points x0 = o + t d of rays with directions v = d, two ways (torch autograd,
    float64): eq. 8, −(∂σ/∂θ)/⟨∇ₓσ(x0), v⟩, and the forward trick, the θ-derivative of
    t(θ) = t0 − σ(x0; θ)/⟨∇ₓσ(x0; θ0), v⟩ with the denominator held fixed.  Returns
    ``(implicit, trick)``, each (n, P) in ``scene.param_vector()`` order."""
    import array_api_compat.torch as xp
    import torch

    theta0 = torch.tensor(scene.param_vector(), dtype=torch.float64)
    x0 = torch.tensor(o + t[:, None] * d, dtype=torch.float64, requires_grad=True)
    v = torch.tensor(d, dtype=torch.float64)
    phi = scene.value(x0, xp, theta0)
    (gx,) = torch.autograd.grad(phi.sum(), x0)  # rows independent: per-point ∂σ/∂x0
    gv = (gx * v).sum(-1)
    x0c = x0.detach()
    jac = torch.autograd.functional.jacobian(lambda th: scene.value(x0c, xp, th), theta0)  # (n, P)
    implicit = -jac / gv[:, None]
    t0 = torch.tensor(t, dtype=torch.float64)
    trick = torch.autograd.functional.jacobian(lambda th: t0 - scene.value(x0c, xp, th) / gv.detach(), theta0)
    return implicit.numpy(), trick.numpy()
