"""Ray families: seeded generators of (origins, unit directions), float64, shape (n, 3)."""

from __future__ import annotations

import numpy as np

from .scene import unit


#: rows divided by their norm; one helper for the whole reference (``scene.unit``)
normalize = unit


def pinhole(eye, look_at, up=(0.0, 1.0, 0.0), fov_deg: float = 40.0, width: int = 64, height: int = 64):
    """Pinhole camera rays through pixel centres, row-major from the top-left pixel.

    The image plane at distance 1 spans tan(fov/2) vertically (fov is the vertical field of
    view, degrees) and keeps square pixels.  Returns ``origins`` (all equal to ``eye``) and
    unit ``directions``.
    """
    eye = np.asarray(eye, np.float64)
    forward = normalize(np.asarray(look_at, np.float64) - eye)
    right = normalize(np.cross(forward, np.asarray(up, np.float64)))
    true_up = np.cross(right, forward)
    half_h = np.tan(np.radians(fov_deg) / 2)
    half_w = half_h * width / height
    u = (np.arange(width) + 0.5) / width * 2 - 1
    v = 1 - (np.arange(height) + 0.5) / height * 2
    uu, vv = np.meshgrid(u * half_w, v * half_h)
    dirs = forward + uu[..., None] * right + vv[..., None] * true_up
    dirs = normalize(dirs.reshape(-1, 3))
    origins = np.broadcast_to(eye, dirs.shape).copy()
    return origins, dirs


def _perp_frames(w: np.ndarray, rng) -> np.ndarray:
    """A random unit vector orthogonal to each unit row of ``w``."""
    p = rng.normal(size=w.shape)
    p -= np.einsum("ij,ij->i", p, w)[:, None] * w
    return normalize(p)


def random_directions(n: int, seed: int) -> np.ndarray:
    """n unit vectors uniform on the sphere (normalised Gaussians)."""
    return normalize(np.random.default_rng(seed).normal(size=(n, 3)))


def impact(n: int, impact_parameter, distance: float, seed: int, center=(0.0, 0.0, 0.0)):
    """Rays from ``distance`` away aimed to pass ``impact_parameter`` (scalar or (n,)) from
    ``center``: o = c + distance·w + b·p, d = −w, w random unit, p ⟂ w random unit.  For a
    sphere of radius 1 at c, b = 1 ± 10⁻ᵏ gives grazing hits and near misses."""
    rng = np.random.default_rng(seed)
    w = normalize(rng.normal(size=(n, 3)))
    p = _perp_frames(w, rng)
    b = np.broadcast_to(np.asarray(impact_parameter, np.float64), (n,))
    o = np.asarray(center, np.float64) + distance * w + b[:, None] * p
    return o, -w


def grazing_pm(n: int, k: float, distance: float, seed: int, radius: float = 1.0, center=(0.0, 0.0, 0.0)):
    """Half the rays at impact parameter r(1 + 10⁻ᵏ) (near misses), half at r(1 − 10⁻ᵏ)
    (grazing hits), alternating."""
    b = radius * (1.0 + np.where(np.arange(n) % 2 == 0, 1.0, -1.0) * 10.0 ** (-k))
    return impact(n, b, distance, seed, center)


def in_ball(n: int, radius: float, seed: int, center=(0.0, 0.0, 0.0)):
    """Origins uniform in the ball of ``radius`` about ``center``, directions uniform."""
    rng = np.random.default_rng(seed)
    u = normalize(rng.normal(size=(n, 3)))
    o = np.asarray(center, np.float64) + radius * rng.uniform(size=(n, 1)) ** (1 / 3) * u
    return o, normalize(rng.normal(size=(n, 3)))


def far(n: int, distance: float, target_radius: float, seed: int):
    """Origins at ``distance`` from the origin in random directions, aimed at random points in
    the ball of ``target_radius`` (so most rays hit an object of that size)."""
    rng = np.random.default_rng(seed)
    o = distance * normalize(rng.normal(size=(n, 3)))
    target = target_radius * rng.uniform(-1, 1, size=(n, 3)) / np.sqrt(3)
    return o, normalize(target - o)
