"""Ray families: seeded generators of (origins, unit directions), float64, shape (n, 3)."""

from __future__ import annotations

import numpy as np


def normalize(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


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
