"""φ of a grid SDF (:class:`reference.grid.GridSDF`) as a Warp kernel, float64.

The formula and its order of operations are :meth:`GridSDF._eval`'s, written per point: grid
coordinates g = (x − lo) ⊘ h, the closest point of the box p = min(max(g, 0), n − 1), the cell
c = min(⌊p⌋, n − 2), local coordinates u = p − c, the trilinear interpolant of the cell's 8
corner samples (lerp along x, then y, then z, each a + (b − a)·s: ``reference.grid._trilerp``)
plus the distance to the box √((q₀² + q₁²) + q₂²), q = (g − p) ⊙ h.  Samples are read from the
C-ordered flat array (index (i·n_y + j)·n_z + k).  Compiled without fused multiply-adds, so φ is
numpy's bit for bit.  A point with a NaN coordinate gives NaN (numpy's clamp propagates it).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .funcs import _max, _min
from .launch import launch_on_points

wp.set_module_options({"fuse_fp": False})  # each operation rounded as numpy rounds it


@wp.func
def _axis(x: wp.float64, lo: wp.float64, h: wp.float64, n: wp.int32):
    """(g, p, cell, u) along one axis."""
    g = (x - lo) / h
    p = _min(_max(g, wp.float64(0.0)), wp.float64(n - 1))
    c = _min(wp.floor(p), wp.float64(n - 2))
    return g, p, c, p - c


@wp.func
def _lerp(a: wp.float64, b: wp.float64, s: wp.float64) -> wp.float64:
    return a + (b - a) * s


@wp.kernel
def grid_phi_points(X: wp.array2d(dtype=wp.float64), V: wp.array(dtype=wp.float64),
                    geo: wp.array(dtype=wp.float64), shape: wp.array(dtype=wp.int32), F: wp.array(dtype=wp.float64)):
    """F[i] = φ(X[i]); ``geo`` = (lo₀, lo₁, lo₂, h₀, h₁, h₂), ``shape`` = (n_x, n_y, n_z)."""
    i = wp.tid()
    nx, ny, nz = shape[0], shape[1], shape[2]
    g0, p0, c0, u0 = _axis(X[i, 0], geo[0], geo[3], nx)
    g1, p1, c1, u1 = _axis(X[i, 1], geo[1], geo[4], ny)
    g2, p2, c2, u2 = _axis(X[i, 2], geo[2], geo[5], nz)
    if (c0 != c0) or (c1 != c1) or (c2 != c2):
        F[i] = wp.float64(wp.nan)
        return
    sx = ny * nz
    b = (wp.int32(c0) * ny + wp.int32(c1)) * nz + wp.int32(c2)
    # corner k = 4a + 2b + c is vertex (i + a, j + b, k + c) (reference.grid._CORNERS)
    v0, v1, v2, v3 = V[b], V[b + 1], V[b + nz], V[b + nz + 1]
    v4, v5, v6, v7 = V[b + sx], V[b + sx + 1], V[b + sx + nz], V[b + sx + nz + 1]
    x00 = _lerp(v0, v4, u0)
    x01 = _lerp(v1, v5, u0)
    x10 = _lerp(v2, v6, u0)
    x11 = _lerp(v3, v7, u0)
    y0 = _lerp(x00, x10, u1)
    y1 = _lerp(x01, x11, u1)
    t = _lerp(y0, y1, u2)
    q0 = (g0 - p0) * geo[3]
    q1 = (g1 - p1) * geo[4]
    q2 = (g2 - p2) * geo[5]
    F[i] = t + wp.sqrt((q0 * q0 + q1 * q1) + q2 * q2)


class WarpGrid:
    """A :class:`GridSDF`'s samples and geometry on ``device``; :meth:`phi_points` as
    :meth:`impls.warp.fields.WarpScene.phi_points`."""

    def __init__(self, grid, device: str):
        self.device = device
        self.values = wp.array(np.ascontiguousarray(grid.values, np.float64).reshape(-1), dtype=wp.float64,
                               device=device)
        self.geo = wp.array(np.concatenate([grid.lo, grid.spacing]).astype(np.float64), dtype=wp.float64,
                            device=device)
        self.shape = wp.array(np.array(grid.shape, np.int32), dtype=wp.int32, device=device)

    def phi_points(self, x: np.ndarray) -> np.ndarray:
        return launch_on_points(grid_phi_points, x, [self.values, self.geo, self.shape], self.device)
