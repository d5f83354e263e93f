"""Grid SDFs: a field sampled on a regular grid and interpolated trilinearly.

This is the field type of most fast systems (voxel SDFs, OpenVDB-style dense grids, SDFs baked
from meshes).  Samples ``values[i, j, k]`` sit at the grid vertices x_ijk = lo + (i, j, k) ⊙ h
(``lo`` the corner, ``h`` the spacing per axis); the box B = [lo, lo + (n − 1) ⊙ h].

Field (per point x, grid coordinates g = (x − lo) ⊘ h):

* p = clamp(g, 0, n − 1) (the closest point of B, in grid coordinates; = g inside B),
* cell c = min(⌊p⌋, n − 2), local coordinates u = p − c ∈ [0, 1]³,
* T(p) = the trilinear interpolant of the cell's 8 corner values (lerp along x, then y, then z),
* φ(x) = T(p) + |(g − p) ⊙ h|, i.e. inside B the trilinear interpolant, outside it the value at
  the closest point of B plus the Euclidean distance to B.

φ is continuous (adjacent cells' interpolants agree on their shared face) and piecewise
polynomial.  It is not an SDF (exact_sdf False): the interpolant of SDF samples is within
O(h²) of the distance, and its slope can exceed 1.

Lipschitz bound (derivation).  In a cell, ∂T/∂x at local (u, v, w) is the bilinear interpolation
in (v, w) of the cell's four x-edge differences (v₁ − v₀)/h_x, so |∂T/∂x| ≤ A_x = the largest
|Δ|/h_x over those edges; likewise A_y, A_z, so |∇T| ≤ √(A_x² + A_y² + A_z²) in the cell, and
L_T is the maximum over cells.  Outside B: at a point whose closest point lies on a face
(one coordinate clamped) ∇φ = ±e_axis + the tangential gradient of T on that face, so
|∇φ|² = 1 + |∇_tan T|²; near an edge (two clamped) ∇φ = (a unit vector normal to the edge) +
(∂T along the edge) e_edge, |∇φ|² = 1 + (∂_e T)²; near a corner |∇φ| = 1.  With G = the
largest per-face-cell bound √(B₁² + B₂²) of the tangential derivatives (Bᵢ as above, over the
face cell's edges), |∇φ| ≤ √(1 + G²) outside B.  φ is continuous and piecewise C¹ on
polyhedral pieces, so L = max(L_T, √(1 + G²)) is a Lipschitz constant on all of ℝ³; it is
computed from the samples and rounded up by 8 ε (SceneInfo.lipschitz, ``domain`` None).

Exact first hits (:meth:`GridSDF.crossings`).  Along a ray x(t) = o + t d the grid coordinates
are affine, g(t) = g₀ + t g', g₀ = (o − lo) ⊘ h, g' = d ⊘ h.  The cells the ray crosses are
visited in order by a 3-D DDA (J. Amanatides and A. Woo, "A fast voxel traversal algorithm for
ray tracing", Eurographics 1987) from the box entry to the box exit; each cell boundary is
computed directly as (plane − g₀ₖ)/g'ₖ (one rounding per operation, not an accumulated
tMax += tDelta).  Ties — a ray through a grid edge or vertex, where two or three boundaries
coincide — advance every tied axis at once: the cells touched only along that edge or at that
vertex meet the ray in a single point, where φ is continuous.  A ray lying *in* a grid plane
takes the cell on the side its index rule picks (⌊g⌋ for g' ≥ 0, ⌈g⌉ − 1 for g' < 0); both
neighbours' interpolants agree on the plane.

In a cell, with s = t − t_a (t_a the entry), T(u(s)) is a cubic: each corner's weight is a
product of three affine functions (1 − uₖ − u'ₖ s or uₖ + u'ₖ s), and its coefficients are
formed in float64 as sums of 8 products of three numbers (relative error a few ε of the sum of
the absolute terms).  The cubic is used only to place *probes*: the cell's end points and the
roots of its derivative (the stable quadratic formula) in between, so that between consecutive
probes the (exact-coefficient) cubic is monotone and has at most one root.  The field is then
evaluated at the probes with the same trilinear formula as :meth:`GridSDF.value` (not with the
cubic, whose coefficients cancel), and every change of the state "φ > 0" between probes is a
bracket, bisected to adjacent floats on that formula.  The returned depth is the *first float64
t at which the float64 φ is on the other side*; its distance to the root of the real-number
trilinear φ is |δφ|/|dφ/dt| with δφ the few-ulp rounding of φ (the problem's own condition).

Tangency.  A ray that touches the surface without crossing has φ ≥ 0 around a critical point of
the cubic.  Decision: it is a hit when the float64 φ at that critical point (a probe) is ≤ 0 —
the same rule as a crossing, "φ ≤ 0 reached" — and a miss when it is > 0.  A pair of crossings
closer together than the rounding of the critical point's position can be missed; that is a
tangency at the resolution of float64, where any method's answer is determined only to O(√ε).

Outside B.  φ = T(p) + dist ≥ m + dist with m the smallest sample on the grid's boundary layer,
so if m > 0 (a *closed* grid: the surface lies strictly inside B) φ > 0 off B and the DDA over B
finds every crossing.  If m ≤ 0 the surface can leave B, where φ contains a square root: such a
grid has ``exact_hits`` False (the case catalog then uses the certified numerical reference,
valid with L above) and :meth:`GridSDF.first_hit` raises.

Parameters.  With ``differentiable=True`` the samples are the node's θ (``own_params``
``values``, C order), so backends differentiate φ and dt/dθ with respect to them by autodiff
and :meth:`jet` gives ∂φ/∂values (the 8 trilinear weights; dense, so only for small grids).
By default θ is empty.
"""

from __future__ import annotations

import functools
import hashlib
import math
from pathlib import Path

import numpy as np

from . import raybounds
from .cases import register_each
from .scene import Field, SceneInfo, _points, const, safe_norm

EPS = np.finfo(np.float64).eps

#: corner k = 4a + 2b + c is vertex (i + a, j + b, k + c) of the cell
_CORNERS = np.array([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)], np.int64)


def _trilerp(c, u):
    """Trilinear interpolation of the corner values ``c`` (..., 8) (corner order of
    :data:`_CORNERS`) at local coordinates ``u`` (..., 3) ∈ [0, 1]³: lerp along x, then y, then
    z, each lerp written a + (b − a)·s.  Pure arithmetic, so it serves numpy, torch and jax."""
    ux, uy, uz = u[..., 0], u[..., 1], u[..., 2]
    x00 = c[..., 0] + (c[..., 4] - c[..., 0]) * ux  # (y, z) = (0, 0)
    x01 = c[..., 1] + (c[..., 5] - c[..., 1]) * ux
    x10 = c[..., 2] + (c[..., 6] - c[..., 2]) * ux
    x11 = c[..., 3] + (c[..., 7] - c[..., 3]) * ux
    y0 = x00 + (x10 - x00) * uy
    y1 = x01 + (x11 - x01) * uy
    return y0 + (y1 - y0) * uz


def _trilerp_grad(c, u):
    """∂T/∂u (..., 3) of :func:`_trilerp`: each component the bilinear interpolation, in the
    other two coordinates, of the cell's edge differences along that axis."""
    ux, uy, uz = u[..., 0], u[..., 1], u[..., 2]

    def bilerp(a00, a01, a10, a11, s, t):  # a_{st}: value at (s, t) ∈ {0,1}²
        b0 = a00 + (a10 - a00) * s
        b1 = a01 + (a11 - a01) * s
        return b0 + (b1 - b0) * t

    v = [c[..., k] for k in range(8)]
    dx = bilerp(v[4] - v[0], v[5] - v[1], v[6] - v[2], v[7] - v[3], uy, uz)
    dy = bilerp(v[2] - v[0], v[3] - v[1], v[6] - v[4], v[7] - v[5], ux, uz)
    dz = bilerp(v[1] - v[0], v[3] - v[2], v[5] - v[4], v[7] - v[6], ux, uy)
    return np.stack([dx, dy, dz], axis=-1)


def _trilerp_weights(u):
    """The 8 trilinear weights Πₖ (uₖ or 1 − uₖ) at ``u`` (n, 3), shape (n, 8): ∂T/∂(corner)."""
    w1 = u[:, None, :]
    w0 = 1.0 - w1
    sel = _CORNERS[None, :, :]
    return np.prod(np.where(sel == 1, w1, w0), axis=2)


class GridSDF(Field):
    """A field sampled on a regular grid, trilinear inside its box, extended outside by the
    distance to the box (formula, Lipschitz bound and exact hits: module docstring).

    ``values``: float64 samples, shape (nx, ny, nz), every nₖ ≥ 2, all finite.
    ``lo``: the grid's corner (3,).  ``spacing``: h > 0, a number or one per axis (3,).
    ``differentiable``: the samples are θ (default False: θ is empty)."""

    kind = "grid"

    def __init__(self, values, lo=(0.0, 0.0, 0.0), spacing=1.0, differentiable: bool = False):
        try:
            v = np.array(values, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"values must be a 3-D array of numbers (nx, ny, nz), got {type(values).__name__}") from None
        if v.ndim != 3 or min(v.shape) < 2:
            raise ValueError(f"values must have shape (nx, ny, nz) with every n ≥ 2 (a grid of at least one cell), "
                             f"got shape {v.shape}")
        bad = ~np.isfinite(v)
        if bad.any():
            first = tuple(int(i) for i in np.argwhere(bad)[0])
            raise ValueError(f"values must be finite: {int(bad.sum())} of {v.size} samples are NaN or inf "
                             f"(first at index {first}); fill them (e.g. with a distance bound) before building the grid")
        lo_a = np.array(lo, dtype=np.float64) if np.ndim(lo) else None
        if lo_a is None or lo_a.shape != (3,) or not np.all(np.isfinite(lo_a)):
            raise ValueError(f"lo (the grid's corner) must be 3 finite numbers, got {lo!r}")
        h = np.array(spacing, dtype=np.float64)
        if h.ndim == 0:
            h = np.full(3, float(h))
        if h.shape != (3,) or not np.all(np.isfinite(h)) or not np.all(h > 0):
            raise ValueError(f"spacing must be a finite number > 0 or 3 such numbers (one per axis), got {spacing!r}")
        if not isinstance(differentiable, (bool, np.bool_)):
            raise ValueError(f"differentiable must be True or False, got {differentiable!r}")
        v.setflags(write=False)
        self.values = v
        self.lo = lo_a
        self.spacing = h
        self.differentiable = bool(differentiable)
        self.shape = tuple(int(s) for s in v.shape)
        self.hi = lo_a + (np.array(self.shape) - 1) * h
        self._cache: dict = {}

    # -- structure -----------------------------------------------------------------------------
    def own_params(self):
        return {"values": self.values} if self.differentiable else {}

    def _rebuild(self, own, children):
        values = np.reshape(np.asarray(own["values"], np.float64), self.shape) if self.differentiable else self.values
        return GridSDF(values, self.lo, self.spacing, self.differentiable)

    def spec(self) -> dict:
        """The grid by its geometry and the SHA-256 of its samples' bytes (equal specs ⇔ equal
        scenes, without a 2^18-number JSON list per case hash)."""
        digest = hashlib.sha256(np.ascontiguousarray(self.values).tobytes()).hexdigest()
        return {"kind": self.kind, "type": type(self).__name__, "params": {}, "children": [],
                "static": {"shape": list(self.shape), "lo": self.lo.tolist(), "spacing": self.spacing.tolist(),
                           "values_sha256": digest, "differentiable": self.differentiable}}

    @property
    def boundary_min(self) -> float:
        """The smallest sample on the grid's boundary layer (the minimum of T over ∂B)."""
        v = self.values
        return float(min(v[0].min(), v[-1].min(), v[:, 0].min(), v[:, -1].min(), v[:, :, 0].min(), v[:, :, -1].min()))

    @property
    def closed(self) -> bool:
        """φ > 0 everywhere off the box (every boundary sample > 0): the DDA sees every hit."""
        return self.boundary_min > 0

    @property
    def lipschitz_bound(self) -> float:
        """L = max(L_T, √(1 + G²)) (module docstring), rounded up by 8 ε."""
        if "L" not in self._cache:
            self._cache["L"] = float(_lipschitz(self.values, self.spacing) * (1 + 8 * EPS))
        return self._cache["L"]

    @property
    def info(self) -> SceneInfo:
        return SceneInfo(exact_sdf=False, lipschitz=self.lipschitz_bound, distance_bound=False, smooth=False,
                         exact_hits=self.closed, exact_normals=True, exact_curvature=False,
                         exact_hit_param_grad=self.differentiable and self.closed)

    def bounding_sphere(self):
        """The box's circumscribed ball grown by max(0, −m) (m = :attr:`boundary_min`): φ ≥ m + dist
        off the box, so φ ≤ 0 needs dist ≤ −m."""
        centre = 0.5 * (self.lo + self.hi)
        return centre, float(np.linalg.norm(0.5 * (self.hi - self.lo))) + max(0.0, -self.boundary_min)

    def ray_bounds(self, xp, o, d):
        """The box grown by max(0, −m) on every side (slab test, padded as in :mod:`reference.raybounds`)."""
        centre, radius = self.bounding_sphere()
        half = 0.5 * (self.hi - self.lo) + max(0.0, -self.boundary_min)
        return raybounds.box_chord(xp, o - const(xp, o, centre), d, half.tolist(), radius)

    # -- evaluation ----------------------------------------------------------------------------
    def _values_like(self, xp, like):
        """The samples, flattened, as an array of ``like``'s library, dtype and device; cached per
        node for numpy and torch (a 64³ grid is 2 MiB: converting it per call, or keying the
        shared constant cache by its bytes, would cost more than φ itself on small batches).
        jax is converted per call (a cached array made while tracing could leak a tracer)."""
        import array_api_compat

        if array_api_compat.is_jax_array(like):
            return xp.asarray(np.array(self.values.reshape(-1)), dtype=like.dtype)
        key = (type(like).__name__, str(like.dtype), str(getattr(like, "device", "")))
        out = self._cache.get(key)
        if out is None:
            flat = self.values.reshape(-1)
            if isinstance(like, np.ndarray):
                out = flat.astype(like.dtype)
            else:
                out = xp.asarray(np.array(flat), dtype=like.dtype, device=like.device)  # a writable copy for torch
            self._cache[key] = out
        return out

    def _eval(self, x, xp, cursor):
        if self.differentiable:
            flat = xp.reshape(cursor.take(self.values), (-1,))
        else:
            flat = self._values_like(xp, x)
        nx, ny, nz = self.shape
        g = (x - const(xp, x, self.lo)) / const(xp, x, self.spacing)
        p = xp.minimum(xp.maximum(g, const(xp, g, np.zeros(3))), const(xp, g, np.array(self.shape) - 1.0))
        cell = xp.minimum(xp.floor(p), const(xp, g, np.array(self.shape) - 2.0))
        u = p - cell
        ic = xp.astype(cell, xp.int64)
        base = (ic[..., 0] * (ny * nz) + ic[..., 1] * nz) + ic[..., 2]
        offsets = (_CORNERS @ np.array([ny * nz, nz, 1])).astype(np.int64)
        idx = base[..., None] + xp.asarray(offsets, dtype=xp.int64, device=_device(base))
        c = xp.reshape(xp.take(flat, xp.reshape(idx, (-1,))), tuple(idx.shape))
        return _trilerp(c, u) + safe_norm(xp, (g - p) * const(xp, g, self.spacing))

    # -- exact answers (float64 numpy) -------------------------------------------------------
    def _locate(self, x):
        """g, p, cell (int), u of points x (n, 3) as in :meth:`_eval`."""
        g = (x - self.lo) / self.spacing
        n = np.array(self.shape)
        p = np.minimum(np.maximum(g, 0.0), n - 1.0)
        cell = np.minimum(np.floor(p), n - 2.0)
        return g, p, cell.astype(np.int64), p - cell

    def _corners(self, cell):
        """Corner values (n, 8) of cells (n, 3)."""
        nx, ny, nz = self.shape
        idx = cell[:, None, :] + _CORNERS[None]
        return self.values.reshape(-1)[(idx[..., 0] * ny + idx[..., 1]) * nz + idx[..., 2]]

    def _jet(self, x):
        """φ, ∇φ and ∂φ/∂θ.  Inside B: ∇φ = ∂T/∂u ⊘ h.  Outside: the clamped axes take the
        distance's gradient (g − p) ⊙ h / |(g − p) ⊙ h|, the others ∂T/∂u ⊘ h at p.  At a cell face
        the cell of :meth:`_eval` (⌊p⌋) gives the one-sided gradient.  ∂φ/∂values: the 8
        trilinear weights scattered into a dense (n, P) row (differentiable grids only)."""
        g, p, cell, u = self._locate(x)
        c = self._corners(cell)
        q = (g - p) * self.spacing
        dist = np.linalg.norm(q, axis=1)
        phi = _trilerp(c, u) + dist
        grad = _trilerp_grad(c, u) / self.spacing
        clamped = g != p
        with np.errstate(invalid="ignore", divide="ignore"):
            grad = np.where(clamped, q / dist[:, None], grad)
        n = x.shape[0]
        if not self.differentiable:
            return phi, grad, np.zeros((n, 0))
        nx, ny, nz = self.shape
        dth = np.zeros((n, self.values.size))
        idx = cell[:, None, :] + _CORNERS[None]
        flat = (idx[..., 0] * ny + idx[..., 1]) * nz + idx[..., 2]
        np.add.at(dth, (np.repeat(np.arange(n), 8), flat.ravel()), _trilerp_weights(u).ravel())
        return phi, grad, dth

    def _require_closed(self):
        if not self.closed:
            raise ValueError(
                f"GridSDF: the smallest boundary sample is {self.boundary_min:.6g} ≤ 0, so the surface may leave the "
                "grid's box, where φ contains a square root and the DDA does not apply; exact hits need every "
                "boundary sample > 0 (pad the grid with a layer of positive values, e.g. grid_from_field on a larger "
                "box), or use reference.numerical.first_hit_numeric with scene.info.lipschitz")

    def crossings(self, o, d, t_min: float = -math.inf, first_only: bool = False) -> list[np.ndarray]:
        """Per ray, the sorted depths t > t_min (at the box entry or later) where the float64 φ
        changes state "φ > 0" (module docstring); with ``first_only`` at most one per ray."""
        self._require_closed()
        o, d = _points(o, "o"), _points(d, "d")
        rays, t = _march(self, o, d, float(t_min), first_only)
        out = [np.zeros(0) for _ in range(o.shape[0])]
        if rays.size:
            order = np.lexsort((t, rays))
            rays, t = rays[order], t[order]
            starts = np.searchsorted(rays, np.arange(o.shape[0] + 1))
            for i in np.flatnonzero(np.diff(starts)):
                out[i] = t[starts[i]:starts[i + 1]]
        return out

    def ray_intervals(self, o, d):
        """{t : φ(o + t d) ≤ 0} as (enter, exit, …): the crossings over the whole box chord (φ > 0
        at the box entry of a closed grid, so they alternate enter/exit).  A float64 touch
        (φ ≤ 0 at one probe only) is an interval of width ≤ 1 ulp."""
        return self.crossings(o, d)

    def first_hit(self, o, d, t_min: float = 0.0):
        """First float64 t > t_min where φ changes state (φ > 0 ↔ φ ≤ 0); inf for a miss.  The
        start state is φ's at max(t_min, box entry); a touch is a hit iff φ ≤ 0 at the touch's
        critical point (module docstring)."""
        self._require_closed()
        o, d = _points(o, "o"), _points(d, "d")
        rays, t = _march(self, o, d, float(t_min), first_only=True)
        out = np.full(o.shape[0], np.inf)
        out[rays] = t
        return out


def _device(a):
    import array_api_compat

    return array_api_compat.device(a)


def _lipschitz(v: np.ndarray, h: np.ndarray) -> float:
    """max(L_T, √(1 + G²)) of the module docstring, from the samples."""

    def edge_max(axis):
        """Per cell, the largest |Δ|/h over the cell's 4 edges along ``axis``: shape (nx−1, ny−1, nz−1)."""
        e = np.abs(np.diff(v, axis=axis)) / h[axis]
        others = [a for a in range(3) if a != axis]
        for a in others:  # max over the two vertex layers of each other axis
            e = np.maximum(np.take(e, range(e.shape[a] - 1), axis=a), np.take(e, range(1, e.shape[a]), axis=a))
        return e

    A = [edge_max(a) for a in range(3)]
    L_T = float(np.sqrt(A[0] ** 2 + A[1] ** 2 + A[2] ** 2).max())
    G = 0.0
    for axis in range(3):
        t1, t2 = [a for a in range(3) if a != axis]
        for end in (0, -1):  # the two faces normal to `axis`: the face cells' tangential edge bounds
            face = np.sqrt(np.take(A[t1], end, axis=axis) ** 2 + np.take(A[t2], end, axis=axis) ** 2)
            G = max(G, float(face.max()))
    return max(L_T, math.sqrt(1.0 + G * G))


def _cell_probe_values(grid, corners, cell, g0, dg, t):
    """φ (float64) at depths ``t`` (k, m) of rays with grid origin g0 (k, 3) and slope dg (k, 3),
    evaluated with the fixed cells ``cell`` (k, 3) and their corners (k, 8): u = g₀ + t g' − c."""
    u = g0[:, None, :] + t[..., None] * dg[:, None, :] - cell[:, None, :]
    return _trilerp(corners[:, None, :], u)


def _cubic_critical_points(corners, ua, dg):
    """Roots s of dT/ds for T(s) = trilinear(corners, ua + s g') (k rays), shape (k, 2), NaN where
    absent.  Cubic coefficients: Σ_corners v · Πₖ (αₖ + βₖ s) with (α, β) = (uₖ, g'ₖ) for a
    corner's upper index and (1 − uₖ, −g'ₖ) for its lower one; derivative 3c₃s² + 2c₂s + c₁ by the
    stable quadratic formula (q = −(B + sign(B)√disc)/2, roots q/A and C/q)."""
    sel = _CORNERS[None]  # (1, 8, 3)
    alpha = np.where(sel == 1, ua[:, None, :], 1.0 - ua[:, None, :])
    beta = np.where(sel == 1, dg[:, None, :], -dg[:, None, :])
    a0, a1, a2 = alpha[..., 0], alpha[..., 1], alpha[..., 2]
    b0, b1, b2 = beta[..., 0], beta[..., 1], beta[..., 2]
    c1 = np.sum(corners * (b0 * a1 * a2 + a0 * b1 * a2 + a0 * a1 * b2), axis=1)
    c2 = np.sum(corners * (b0 * b1 * a2 + b0 * a1 * b2 + a0 * b1 * b2), axis=1)
    c3 = np.sum(corners * (b0 * b1 * b2), axis=1)
    A, B, C = 3.0 * c3, 2.0 * c2, c1
    out = np.full((ua.shape[0], 2), np.nan)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        disc = B * B - 4.0 * A * C
        q = -0.5 * (B + np.copysign(np.sqrt(np.where(disc >= 0, disc, np.nan)), B))
        quad = A != 0
        out[:, 0] = np.where(quad, q / A, np.where(B != 0, -C / B, np.nan))
        out[:, 1] = np.where(quad & (q != 0), C / q, np.nan)
    return out


def _march(grid: GridSDF, o, d, t_min: float, first_only: bool):
    """DDA over the box for all rays at once (one cell per ray per step), collecting brackets of
    state changes of φ > 0, then bisecting them together.  Returns (ray index, t) arrays."""
    n = np.array(grid.shape)
    h, lo = grid.spacing, grid.lo
    g0_all = (o - lo) / h
    dg_all = d / h
    # box entry/exit in grid coordinates (closed box, so rays along a boundary plane are traced)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        ta = (0.0 - g0_all) / dg_all
        tb = (n - 1.0 - g0_all) / dg_all
    par = dg_all == 0
    inside_par = (g0_all >= 0) & (g0_all <= n - 1)
    t_in = np.where(par, np.where(inside_par, -np.inf, np.inf), np.fmin(ta, tb))
    t_out = np.where(par, np.where(inside_par, np.inf, -np.inf), np.fmax(ta, tb))
    t0 = np.max(t_in, axis=1)
    t1 = np.min(t_out, axis=1)
    t_start = np.maximum(t0, t_min)
    live = np.flatnonzero(t_start <= t1)

    br_ray, br_lo, br_hi, br_cell, br_state = [], [], [], [], []
    if live.size:
        g0, dg, t_a, t_end = g0_all[live], dg_all[live], t_start[live], t1[live]
        gs = g0 + t_a[:, None] * dg
        cell = np.where(dg >= 0, np.floor(gs), np.ceil(gs) - 1.0)
        cell = np.clip(cell, 0, n - 2).astype(np.int64)
        step = np.where(dg > 0, 1, np.where(dg < 0, -1, 0))
        corners = grid._corners(cell)
        state = _cell_probe_values(grid, corners, cell, g0, dg, t_a[:, None])[:, 0] > 0
        rid = live
        for _ in range(int(n.sum()) + 8):  # each step advances ≥ 1 index monotonically: ≤ Σ(n − 2) + 1 steps
            if rid.size == 0:
                break
            with np.errstate(divide="ignore", invalid="ignore"):
                plane = np.where(dg > 0, cell + 1.0, cell.astype(np.float64))
                t_next = np.where(dg != 0, (plane - g0) / dg, np.inf)
            t_b = np.minimum(np.min(t_next, axis=1), t_end)
            t_b = np.maximum(t_b, t_a)
            ua = g0 + t_a[:, None] * dg - cell
            crit = _cubic_critical_points(corners, ua, dg)
            crit = np.where((crit > 0) & (crit < (t_b - t_a)[:, None]), t_a[:, None] + crit, np.nan)
            crit = np.sort(crit, axis=1)  # NaNs last
            probes = np.concatenate([t_a[:, None], crit, t_b[:, None]], axis=1)
            probes = np.where(np.isnan(probes), t_b[:, None], probes)
            probes = np.maximum.accumulate(probes, axis=1)  # non-decreasing (rounding of t_a + s)
            st = _cell_probe_values(grid, corners, cell, g0, dg, probes) > 0
            prev = np.concatenate([state[:, None], st[:, :-1]], axis=1)
            flips = st != prev  # flip at column k: bracket (probe[k−1], probe[k]] (k = 0: at t_a)
            lo_t = np.concatenate([t_a[:, None], probes[:, :-1]], axis=1)
            if first_only:
                has = flips.any(axis=1)
                k = np.argmax(flips, axis=1)
                r = np.flatnonzero(has)
                br_ray.append(rid[r])
                br_lo.append(lo_t[r, k[r]])
                br_hi.append(probes[r, k[r]])
                br_cell.append(cell[r])
                br_state.append(prev[r, k[r]])
            else:
                r, k = np.nonzero(flips)
                br_ray.append(rid[r])
                br_lo.append(lo_t[r, k])
                br_hi.append(probes[r, k])
                br_cell.append(cell[r])
                br_state.append(prev[r, k])
                has = np.zeros(rid.size, bool)
            state = st[:, -1]
            # advance: every axis whose boundary is (tied for) the nearest steps at once
            tied = (t_next <= t_b[:, None]) & (step != 0)
            new_cell = cell + np.where(tied, step, 0)
            ok = (~has) & (t_b < t_end) & np.all((new_cell >= 0) & (new_cell <= n - 2), axis=1) & tied.any(axis=1)
            keep = np.flatnonzero(ok)
            rid, g0, dg, t_end, step, state = rid[keep], g0[keep], dg[keep], t_end[keep], step[keep], state[keep]
            t_a, cell = t_b[keep], new_cell[keep]
            corners = grid._corners(cell)
    if not br_ray:
        return np.zeros(0, np.int64), np.zeros(0)
    rays = np.concatenate(br_ray)
    lo_t, hi_t = np.concatenate(br_lo), np.concatenate(br_hi)
    cells, s_lo = np.concatenate(br_cell), np.concatenate(br_state)
    if rays.size == 0:
        return rays, lo_t
    corners = grid._corners(cells)
    g0, dg = g0_all[rays], dg_all[rays]
    for _ in range(2100):  # bisection to adjacent floats (≈ 60 halvings inside one cell)
        mid = lo_t + (hi_t - lo_t) / 2
        active = (mid > lo_t) & (mid < hi_t)
        if not active.any():
            break
        same = (_cell_probe_values(grid, corners, cells, g0, dg, mid[:, None])[:, 0] > 0) == s_lo
        lo_t = np.where(active & same, mid, lo_t)
        hi_t = np.where(active & ~same, mid, hi_t)
    return rays, hi_t


def grid_from_field(field: Field, lo, hi, n, differentiable: bool = False) -> GridSDF:
    """A :class:`GridSDF` of ``field``'s values at the vertices of the regular grid with corners
    ``lo``, ``hi`` (3,) and ``n`` vertices per axis (an int ≥ 2 or three of them): spacing
    (hi − lo)/(n − 1) per axis, samples φ(lo + (i, j, k) ⊙ h) evaluated in float64 numpy."""
    lo_a, hi_a = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    if lo_a.shape != (3,) or hi_a.shape != (3,) or not (np.all(np.isfinite(lo_a)) and np.all(np.isfinite(hi_a))):
        raise ValueError(f"lo and hi must be 3 finite numbers each, got lo={lo!r}, hi={hi!r}")
    if not np.all(hi_a > lo_a):
        raise ValueError(f"hi must exceed lo on every axis (the grid's box), got lo={lo!r}, hi={hi!r}")
    counts = np.broadcast_to(np.asarray(n), (3,))
    if counts.dtype.kind not in "iu" or np.any(counts < 2):
        raise ValueError(f"n must be a whole number ≥ 2 of vertices per axis, or three of them, got {n!r}")
    h = (hi_a - lo_a) / (counts - 1)
    axes = [lo_a[k] + np.arange(counts[k]) * h[k] for k in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    values = np.asarray(field.value(pts.reshape(-1, 3)), np.float64).reshape(tuple(int(c) for c in counts))
    return GridSDF(values, lo_a, h, differentiable)


def _tangent_offsets(grid: GridSDF, centre_dirs, lateral, s_hit: float, s_miss: float, n_iter: int = 200):
    """Per ray family member, the lateral offset s* where rays o(s) = centre + s·lateral − 3·d, d
    = ``centre_dirs``, pass from hitting to missing ``grid``: bisection on the exact hit/miss
    (adjacent floats), so rays at s*(1 ± δ) graze the grid's own surface."""
    lo = np.full(len(centre_dirs), s_hit)
    hi = np.full(len(centre_dirs), s_miss)
    for _ in range(n_iter):
        mid = lo + (hi - lo) / 2
        active = (mid > lo) & (mid < hi)
        if not active.any():
            break
        o = mid[:, None] * lateral - 3.0 * centre_dirs
        hit = np.isfinite(grid.first_hit(o, centre_dirs))
        lo = np.where(active & hit, mid, lo)
        hi = np.where(active & ~hit, mid, hi)
    return lo


#: the structural tags of a grid case's scene (:func:`reference.cases.case_tags` of a :class:`GridSDF`)
GRID_SCENE_TAGS = ("grid", "lipschitz")


#: the grazing case's tangent offsets, stored with the key of what they were computed from
#: (:func:`_grazing_key`): the bisection takes ~2–4 s (51 exact grid marches of 256 rays), which
#: every process that built the case paid, ``bench cases`` included
GRAZING_OFFSETS = Path(__file__).with_name("data") / "grid_torus64_grazing_offsets.npz"


def _grazing_family():
    """(grid, directions, lateral unit vectors) of the grazing case's 256 rays in the equatorial
    plane."""
    rng = np.random.default_rng(90)
    m = 256
    phase = rng.uniform(0, 2 * np.pi, m)
    dirs = np.stack([-np.sin(phase), np.cos(phase), np.zeros(m)], axis=1)
    lateral = np.stack([np.cos(phase), np.sin(phase), np.zeros(m)], axis=1)
    return stored_torus_grid(64), dirs, lateral


def _grazing_key(grid: GridSDF, dirs, lateral) -> str:
    """SHA-256 of everything the offsets depend on: the grid's values, origin and spacing, the
    rays' directions and lateral vectors (a platform whose sin, cos or φ round differently gets
    another key, and computes its own offsets).  A change of the bisection's code is caught by
    tests/test_grid_reference.py, which recomputes them."""
    h = hashlib.sha256()
    for a in (grid.values, grid.lo, grid.spacing, dirs, lateral):
        h.update(np.ascontiguousarray(a, np.float64).tobytes())
    return h.hexdigest()


def _grazing_offsets(stored: bool = True) -> np.ndarray:
    """The lateral offsets s* where the grazing family's rays stop hitting the 64³ grid torus
    (:func:`_tangent_offsets`): read from :data:`GRAZING_OFFSETS` where its key is this
    platform's and ``stored``, else computed."""
    grid, dirs, lateral = _grazing_family()
    key = _grazing_key(grid, dirs, lateral)
    if stored and GRAZING_OFFSETS.exists():
        with np.load(GRAZING_OFFSETS) as f:
            if str(f["key"]) == key:
                return np.array(f["s_star"])
    return _tangent_offsets(grid, dirs, lateral, 1.0, 1.5)


def write_grazing_offsets() -> None:
    """Recompute :data:`GRAZING_OFFSETS` and store them with their key (atomically):
    ``python -c "from reference.grid import write_grazing_offsets as w; w()"``."""
    grid, dirs, lateral = _grazing_family()
    tmp = GRAZING_OFFSETS.with_suffix(".tmp.npz")
    np.savez(tmp, s_star=_grazing_offsets(stored=False), key=np.array(_grazing_key(grid, dirs, lateral)))
    tmp.replace(GRAZING_OFFSETS)


def _grazing_rays():
    """Rays in the equatorial plane at (1 ± 1e-6) × the lateral offset where they stop hitting the
    64³ grid torus (:func:`_grazing_offsets`)."""
    _, dirs, lateral = _grazing_family()
    s_star = _grazing_offsets()
    sgn = np.where(np.arange(len(dirs)) % 2 == 0, 1.0, -1.0)
    s = s_star * (1 + sgn * 1e-6)
    return s[:, None] * lateral - 3.0 * dirs, dirs


def _grid_specs() -> dict:
    """id → (grid vertices per axis, rays() → (origins, directions), the case's own tags,
    description) of every grid case, in catalog order."""
    from . import rays as _rays
    from .cases import LARGE_SIZES, large_tags

    def cam(n):
        return lambda: _rays.pinhole(eye=(0.0, -2.5, 1.8), look_at=(0.0, 0.0, 0.0), fov_deg=40.0, width=n, height=n)

    specs = {f"grid.torus{k}.camera.32x32": (k, cam(32), ("camera",),
                                             f"torus R = 1, r = 0.25 sampled on a {k}³ grid over [−1.4, 1.4]³ "
                                             "(trilinear), seen obliquely by a 32×32 camera")
             for k in (32, 64)}
    specs["grid.torus64.grazing.1e-6"] = (
        64, _grazing_rays, ("grazing",),
        "rays in the equatorial plane at (1 ± 1e-6) × the offset where they stop hitting the 64³ grid "
        "torus (found by bisection on its exact hits): grazing the grid's own outer equator")
    for n in LARGE_SIZES:
        specs[f"grid.torus64.camera.{n}x{n}"] = (64, cam(n), large_tags(n), f"the 64³ grid torus seen obliquely by "
                                                 f"a {n}×{n} camera (the 32×32 view at scale)")
    return specs


@functools.cache
def stored_torus_grid(k: int) -> GridSDF:
    """The torus (R = 1, r = 0.25) sampled on a k³ grid over [−1.4, 1.4]³ (every boundary sample
    ≥ 0.15 > 0: closed), one instance per process."""
    from .primitives import Torus

    return grid_from_field(Torus(1.0, 0.25), (-1.4,) * 3, (1.4,) * 3, k)


_GRID_SPECS = _grid_specs()
#: the ids :func:`grid_case` builds, registered in the catalog at import (tags declared: a suite
#: chosen by tag builds none it does not run)
GRID_CASE_IDS = tuple(_GRID_SPECS)


def grid_case(case_id: str):
    """The grid case ``case_id`` (one of :data:`GRID_CASE_IDS`): the torus grid of its id (32³
    or 64³) seen by a camera, or rays grazing the 64³ grid's own surface in the equatorial plane."""
    from .cases import make_case

    k, rays, tags, description = _GRID_SPECS[case_id]
    return make_case(case_id, stored_torus_grid(k), *rays(), tags=tags, description=description)


def grid_cases():
    """Every grid case of the catalog (:data:`GRID_CASE_IDS`)."""
    from .cases import get_case

    return [get_case(cid) for cid in GRID_CASE_IDS]


register_each({cid: GRID_SCENE_TAGS + spec[2] for cid, spec in _GRID_SPECS.items()}, grid_case)

__all__ = ["GRID_CASE_IDS", "GridSDF", "grid_case", "grid_cases", "grid_from_field", "stored_torus_grid"]
