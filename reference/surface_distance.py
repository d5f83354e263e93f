"""Distances between a triangle mesh and a scene's exact surface ∂Ω = {φ = 0}, in float64.

Used to score surface extraction (marching cubes, :mod:`bench.extraction`).  With M the mesh
and S = ∂Ω:

* mesh → surface:  d_S(x) = min_{y ∈ S} |x − y| at sample points x of M (its vertices and a
  barycentric grid on every face, :func:`mesh_samples`);
* surface → mesh:  d_M(y) = min_{x ∈ M} |y − x| at sample points y of S
  (:func:`surface_samples`), from libigl's AABB tree (``igl.point_mesh_squared_distance``);
* Hausdorff  H = max(max_x d_S(x), max_y d_M(y))  (symmetric, the max of the two directed ones);
* Chamfer    C = ½ (mean_M d_S + mean_S d_M)  (the mean of the two directed *means* of unsquared
  distances; the mesh-side mean is area-weighted, see :func:`mesh_samples`).

How d_S is computed (:func:`distance_to_surface`):

* exact SDF (``scene.info.exact_sdf``): d_S(x) = |φ(x)|, exact up to rounding;
  :class:`reference.mesh.MeshSDF`: the unsigned distance from libigl's AABB tree (the same
  number without the sign test, which distances do not need).
* otherwise, a scene with a Lipschitz bound L (certified fallback): a lower bound
  |φ(x)|/L ≤ d_S(x) (L-Lipschitz φ changes by at most L|x − y| between x and a zero y), and an
  upper bound from a sign change: Newton steps along the line x + t u, u = −sign φ(x) ∇φ/|∇φ|
  (∇φ by central differences: only the direction depends on it), then a bracket [a, b] with
  sign φ(x + a u) = sign φ(x) ≠ sign φ(x + b u) (bisection where Newton's bracket fails).  By
  the intermediate value theorem a zero lies on the segment, so d_S(x) ≤ b.  The value
  reported is b, with the bound b − |φ(x)|/L on its error; it is loose where |∇φ| is far from L
  (|x|² − 1 with L = 13: about 0.85 d), tight for distance bounds (CSG of SDFs) outside.

Sampling error.  A sampled directed maximum is a *lower* bound of the true one.  Both distance
functions are 1-Lipschitz, so the true maximum exceeds the sampled one by at most the covering
radius ρ of the samples (every point of M or S lies within ρ of a sample): the functions return
ρ for each side.  On smooth parts, where the maximum sits at a stationary point of the distance,
the gap is O(ρ² κ) instead (κ the curvature scale), far below ρ.

References: the Hausdorff/Chamfer convention of mesh-extraction benchmarks, e.g. Mescheder et
al., "Occupancy Networks", CVPR 2019 (Chamfer as the mean of the two directed means);
libigl (Jacobson et al., https://libigl.github.io) for point–mesh distances.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from .scene import Field

EPS = float(np.finfo(np.float64).eps)


def _scale(scene: Field) -> tuple[np.ndarray, float]:
    ball = scene.bounding_sphere()
    if ball is None:
        raise ValueError(f"{type(scene).__name__} has no bounding sphere (scene.bounding_sphere() is None); "
                         "surface distances need a bounded surface")
    return np.asarray(ball[0], np.float64), float(ball[1])


def _mesh_of(scene: Field):
    from .mesh import MeshSDF

    return scene if isinstance(scene, MeshSDF) else None


def distance_method(scene: Field) -> str | None:
    """How :func:`distance_to_surface` measures ``scene``: ``"mesh"`` (libigl distance to the
    exact mesh), ``"exact_sdf"`` (|φ|), ``"lipschitz_bracket"`` (the certified fallback), or
    ``None`` when it cannot (not an exact SDF and no Lipschitz bound)."""
    if _mesh_of(scene) is not None:
        return "mesh"
    info = scene.info
    if info.exact_sdf:
        return "exact_sdf"
    if info.lipschitz is not None and math.isfinite(info.lipschitz) and info.lipschitz > 0:
        return "lipschitz_bracket"
    return None


def _phi(scene: Field, x: np.ndarray) -> np.ndarray:
    return np.asarray(scene.value(np.ascontiguousarray(x, np.float64), np), np.float64)


def _grad_fd(scene: Field, x: np.ndarray, step: float) -> np.ndarray:
    """∇φ by central differences (only a search direction: the certificate is a sign change)."""
    g = np.empty_like(x)
    for k in range(3):
        e = np.zeros(3)
        e[k] = step
        g[:, k] = (_phi(scene, x + e) - _phi(scene, x - e)) / (2 * step)
    return g


def _bracket_project(scene: Field, x: np.ndarray, phi0: np.ndarray, size: float, newton_steps: int = 8,
                     bisections: int = 80) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per point x with φ(x) = phi0 ≠ 0: a direction u and a bracket [a, b] along x + t u with a
    sign change of φ (sign at a = sign φ(x), at b the other), b − a ≤ 1e-13 · size where
    bisection converged.  Returns ``(u, a, b)``; b = inf where no sign change was found within
    4 · size."""
    n = x.shape[0]
    g = _grad_fd(scene, x, 1e-7 * size)
    gn = np.linalg.norm(g, axis=1)
    bad = ~(gn > 0) | ~np.isfinite(gn)
    g[bad] = 1.0  # any direction: the bracket search below certifies or gives up
    gn = np.linalg.norm(g, axis=1)
    s = np.sign(phi0)
    u = -s[:, None] * g / gn[:, None]
    t = np.abs(phi0) / gn
    for _ in range(newton_steps):
        y = x + t[:, None] * u
        f = _phi(scene, y)
        df = np.einsum("ij,ij->i", _grad_fd(scene, y, 1e-7 * size), u)
        ok = np.isfinite(f) & np.isfinite(df) & (np.abs(df) > 0)
        t = np.where(ok, t - np.where(ok, f, 0.0) / np.where(ok, df, 1.0), t)
        t = np.clip(t, 0.0, 4 * size)
    # a tight bracket around Newton's answer, verified by signs
    a = t * (1 - 1e-12) - 1e-15 * size
    b = t * (1 + 1e-12) + 1e-15 * size
    a = np.maximum(a, 0.0)
    fa = np.where(a > 0, _phi(scene, x + a[:, None] * u), phi0)
    fb = _phi(scene, x + b[:, None] * u)
    good = (np.sign(fa) == s) & (np.sign(fb) != s)
    # elsewhere: march out from 0 in steps of |φ|/L-size doublings until the sign changes, then bisect
    idx = np.flatnonzero(~good)
    if idx.size:
        lo = np.zeros(idx.size)
        hi = np.maximum(np.abs(t[idx]), 1e-3 * size)
        found = np.zeros(idx.size, bool)
        for _ in range(40):
            f = _phi(scene, x[idx] + hi[:, None] * u[idx])
            now = ~found & (np.sign(f) != s[idx])
            found |= now
            grow = ~found
            lo = np.where(grow, hi, lo)
            hi = np.where(grow, np.minimum(2 * hi, 4 * size), hi)
            if found.all() or np.all(hi[grow] >= 4 * size):
                break
        for _ in range(bisections):
            m = 0.5 * (lo + hi)
            f = _phi(scene, x[idx] + m[:, None] * u[idx])
            same = np.sign(f) == s[idx]
            lo = np.where(same, m, lo)
            hi = np.where(same, hi, m)
            if np.all(hi - lo <= 1e-13 * size):
                break
        a[idx] = lo
        b[idx] = np.where(found, hi, np.inf)
    return u, a, b


def distance_to_surface(scene: Field, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(d (n,), err (n,))``: the distance from each point (n, 3) to the surface φ = 0 and a
    bound on its error |d − d_S| (module docstring).  Exact SDFs and meshes: err is the
    rounding, 8 ε (|x|∞ + radius).  Fallback: d is the certified upper bound b, err = b − |φ|/L
    (NaN where the declared L is refuted by |φ|/L > b, i.e. L understated).  ValueError for a
    scene that :func:`distance_method` cannot measure."""
    x = np.ascontiguousarray(points, np.float64)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"points must have shape (n, 3), got {x.shape}")
    method = distance_method(scene)
    centre, radius = _scale(scene)
    rounding = 8 * EPS * (np.max(np.abs(x), axis=1, initial=0.0) + radius + np.max(np.abs(centre)))
    if method == "mesh":
        import igl

        mesh = _mesh_of(scene)
        d2, _, _ = igl.point_mesh_squared_distance(x, mesh.vertices, mesh.faces)
        return np.sqrt(d2), rounding
    if method == "exact_sdf":
        return np.abs(_phi(scene, x)), rounding
    if method is None:
        raise ValueError(f"{type(scene).__name__} is neither an exact SDF nor states a Lipschitz bound "
                         "(scene.info.lipschitz): its distance to the surface cannot be bounded")
    L = float(scene.info.lipschitz)
    phi0 = _phi(scene, x)
    d = np.zeros(x.shape[0])
    err = np.array(rounding)
    nz = phi0 != 0
    if nz.any():
        _, _, b = _bracket_project(scene, x[nz], phi0[nz], 2 * radius)
        lower = np.abs(phi0[nz]) / L
        d[nz] = b
        e = b - lower
        err[nz] = np.where(e >= -rounding[nz], np.maximum(e, 0.0) + rounding[nz], np.nan)
    return d, err


@dataclasses.dataclass
class SurfaceSamples:
    """Points on (or within ``err`` of) the surface, and ρ: every surface point lies within
    ``covering_radius`` of one of them (certified for meshes and exact SDFs; for the fallback
    an estimate, see :func:`surface_samples`).  ``weights`` sum to 1 (area weights for meshes,
    uniform otherwise)."""

    points: np.ndarray
    weights: np.ndarray
    covering_radius: float
    err: float
    certified_cover: bool


def _triangle_grid(V: np.ndarray, F: np.ndarray, levels: np.ndarray):
    """Barycentric grid points (i/k, j/k, 1 − (i+j)/k), i + j ≤ k, on each face with its own level
    k (``levels`` (m,)), and per-point area weights (face area / points of the face)."""
    pts, w = [], []
    area = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    for k in np.unique(levels):
        sel = np.flatnonzero(levels == k)
        ij = np.array([(i, j) for i in range(k + 1) for j in range(k + 1 - i)], np.float64) / k
        bary = np.column_stack([ij, 1.0 - ij.sum(axis=1)])  # (p, 3)
        tri = V[F[sel]]  # (f, 3, 3)
        pts.append(np.einsum("pk,fkd->fpd", bary, tri).reshape(-1, 3))
        w.append(np.repeat(area[sel] / bary.shape[0], bary.shape[0]))
    p, wt = np.concatenate(pts), np.concatenate(w)
    total = wt.sum()
    return p, (wt / total if total > 0 else np.full(wt.size, 1.0 / max(wt.size, 1)))


def mesh_samples(vertices: np.ndarray, faces: np.ndarray, level: int = 3):
    """Sample points of a triangle mesh: the barycentric grid of ``level`` on every face (its
    vertices, ``level − 1`` points inside each edge, the rest inside), ``(points, weights,
    covering_radius)``.  Weights: face area / points per face, normalised (an area-weighted
    mean).  Covering radius: max over faces of longest edge / level (each sub-triangle's
    diameter; every point of a face lies in one of them)."""
    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64)
    if level < 1:
        raise ValueError(f"level must be ≥ 1 (points per face edge − 1), got {level}")
    if F.shape[0] == 0:
        return np.zeros((0, 3)), np.zeros(0), math.inf
    p, w = _triangle_grid(V, F, np.full(F.shape[0], level))
    e = np.stack([V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 1]], V[F[:, 0]] - V[F[:, 2]]], axis=1)
    longest = float(np.sqrt(np.max(np.sum(e * e, axis=2))))
    return p, w, longest / level


def surface_samples(scene: Field, spacing: float, max_points: int = 4_000_000) -> SurfaceSamples:
    """Points on the exact surface with covering radius about ``spacing``.

    * :class:`reference.mesh.MeshSDF`: a barycentric grid on each exact face with level
      k_f = ⌈longest edge / spacing⌉, area weights; ρ ≤ spacing, exact points.
    * Other scenes: narrow-band refinement of a cell grid over the bounding sphere's cube (a
      cell of half-diagonal r whose centre has |φ| > L r holds no surface point, φ being
      L-Lipschitz; the rest split into 8 until the cell edge s ≤ spacing/√3), then the centres
      projected: with ``closest_point_exact`` for exact SDFs, else by the certified bracket of
      :func:`distance_to_surface` (the point b, within b − a of a zero).  Every surface point y
      lies in a kept cell whose centre g has |g − y| ≤ s√3/2, and the closest point p(g) has
      |p(g) − g| ≤ |g − y|, so |p(g) − y| ≤ s√3 ≤ spacing: certified for exact SDFs.  For the
      fallback it is an estimate: the foot point along ∇φ is not the closest point, and the
      band uses the slope min(L, 1.25 |∇φ(g)|) instead of L (a declared L far above the slope
      near the surface would multiply the samples by L/|∇φ|).

    ValueError if more than ``max_points`` samples would be needed (raise ``spacing``)."""
    if not (spacing > 0 and math.isfinite(spacing)):
        raise ValueError(f"spacing must be a positive length, got {spacing!r}")
    mesh = _mesh_of(scene)
    if mesh is not None:
        V, F = mesh.vertices, mesh.faces
        e = np.stack([V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 1]], V[F[:, 0]] - V[F[:, 2]]], axis=1)
        longest = np.sqrt(np.max(np.sum(e * e, axis=2), axis=1))
        levels = np.maximum(1, np.ceil(longest / spacing)).astype(np.int64)
        n = int(np.sum((levels + 1) * (levels + 2) // 2))
        if n > max_points:
            raise ValueError(f"surface_samples: spacing {spacing:g} needs {n} points on mesh {mesh.name!r} "
                             f"(max_points {max_points}); raise spacing")
        p, w = _triangle_grid(V, F, levels)
        return SurfaceSamples(p, w, float(np.max(longest / levels)), 8 * EPS * mesh.size, True)

    method = distance_method(scene)
    if method is None:
        raise ValueError(f"{type(scene).__name__} is neither an exact SDF nor states a Lipschitz bound: "
                         "its surface cannot be sampled with a guarantee")
    L = 1.0 if method == "exact_sdf" else float(scene.info.lipschitz)
    centre, radius = _scale(scene)
    target = spacing / math.sqrt(3.0)
    n0 = 16
    s = 2 * radius / n0
    g = (np.arange(n0) + 0.5) * s - radius
    cells = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3) + centre
    children = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], np.float64)
    while True:
        phi = _phi(scene, cells)
        slope = L
        if method != "exact_sdf":
            # a declared L far above |∇φ| near the surface (|x|² − 1: L = 13, |∇φ| ≈ 2) would keep a
            # band L/|∇φ| times too wide; the fallback's cover is an estimate anyway, so the band
            # uses min(L, 1.25 |∇φ(centre)|) (the first-order distance |φ|/|∇φ| with a margin)
            slope = np.minimum(L, 1.25 * np.linalg.norm(_grad_fd(scene, cells, 1e-7 * radius), axis=1))
        keep = ~(np.abs(phi) > slope * s * math.sqrt(3.0) / 2)  # NaN φ: kept (cannot exclude)
        cells, phi = cells[keep], phi[keep]
        if s <= target:
            break
        if cells.shape[0] * 8 > max_points:
            raise ValueError(f"surface_samples: spacing {spacing:g} needs more than {max_points} points on "
                             f"{type(scene).__name__}; raise spacing")
        s /= 2
        cells = (cells[:, None, :] + children[None] * (s / 2)).reshape(-1, 3)
    if method == "exact_sdf":
        p = np.asarray(scene.closest_point_exact(cells), np.float64)
        # rounding of x − φ∇φ: a few ε of the coordinates
        err = 8 * EPS * (radius + float(np.max(np.abs(centre))) + 2 * s)
        cert = True
    else:
        nz = phi != 0
        p = cells.copy()
        err = 0.0
        if nz.any():
            u, a, b = _bracket_project(scene, cells[nz], phi[nz], 2 * radius)
            found = np.isfinite(b)
            p[nz] = cells[nz] + np.where(found, b, 0.0)[:, None] * u
            keep = np.ones(cells.shape[0], bool)
            keep[np.flatnonzero(nz)[~found]] = False  # no zero found along its line: no sample
            p = p[keep]
            err = float(np.max((b - a)[found], initial=0.0))
        cert = False
    w = np.full(p.shape[0], 1.0 / max(p.shape[0], 1))
    return SurfaceSamples(p, w, s * math.sqrt(3.0), err, cert)


def mesh_to_surface_errors(scene: Field, vertices: np.ndarray, faces: np.ndarray, spacing: float,
                           level: int = 3, surface: SurfaceSamples | None = None) -> dict:
    """Hausdorff and Chamfer distances between the mesh (``vertices`` (n, 3), ``faces`` (m, 3))
    and the exact surface of ``scene`` (module docstring for the conventions).

    ``spacing``: the surface samples' covering radius (:func:`surface_samples`; pass ``surface``
    to reuse samples).  ``level``: the barycentric grid on the mesh's faces.  Returns a dict:
    ``hausdorff``, ``chamfer``, the directed ``hausdorff_mesh_to_surface``,
    ``hausdorff_surface_to_mesh``, ``chamfer_mesh_to_surface``, ``chamfer_surface_to_mesh``,
    ``distances`` (all pointwise distances, both sides), ``n_mesh_samples``,
    ``n_surface_samples``, ``covering_mesh``, ``covering_surface`` (the ρ of each side),
    ``surface_cover_certified``, ``reference_error_bound`` (max error of the distances
    themselves), ``distance_method``.  An empty mesh has infinite distances."""
    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64)
    if surface is None:
        surface = surface_samples(scene, spacing)
    out = {"n_surface_samples": int(surface.points.shape[0]), "covering_surface": float(surface.covering_radius),
           "surface_cover_certified": bool(surface.certified_cover), "distance_method": distance_method(scene)}
    if F.shape[0] == 0:
        inf = math.inf
        return {**out, "hausdorff": inf, "chamfer": inf, "hausdorff_mesh_to_surface": inf,
                "hausdorff_surface_to_mesh": inf, "chamfer_mesh_to_surface": inf, "chamfer_surface_to_mesh": inf,
                "distances": np.zeros(0), "n_mesh_samples": 0, "covering_mesh": inf,
                "reference_error_bound": float(surface.err)}
    mp, mw, mrho = mesh_samples(V, F, level)
    d_ms, err_ms = distance_to_surface(scene, mp)
    import igl

    d2, _, _ = igl.point_mesh_squared_distance(np.ascontiguousarray(surface.points), V, F)
    d_sm = np.sqrt(d2)
    # libigl's closest point rounds like the coordinates; the samples themselves are off by err
    err_sm = float(surface.err) + 8 * EPS * (float(np.max(np.abs(surface.points), initial=0.0)) + 1.0)
    h_ms, h_sm = float(np.max(d_ms)), float(np.max(d_sm, initial=0.0))
    c_ms, c_sm = float(np.sum(mw * d_ms)), float(np.sum(surface.weights * d_sm))
    ref = float(np.max(err_ms)) if np.all(np.isfinite(err_ms)) else math.nan
    return {**out, "hausdorff": max(h_ms, h_sm), "chamfer": 0.5 * (c_ms + c_sm),
            "hausdorff_mesh_to_surface": h_ms, "hausdorff_surface_to_mesh": h_sm,
            "chamfer_mesh_to_surface": c_ms, "chamfer_surface_to_mesh": c_sm,
            "distances": np.concatenate([d_ms, d_sm]), "n_mesh_samples": int(mp.shape[0]),
            "covering_mesh": float(mrho), "reference_error_bound": max(ref, err_sm) if not math.isnan(ref) else ref}


__all__ = ["SurfaceSamples", "distance_method", "distance_to_surface", "mesh_samples", "mesh_to_surface_errors",
           "surface_samples"]
