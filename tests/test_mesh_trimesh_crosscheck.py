"""Every mesh case against a second, independent reference: trimesh's float64 ray–triangle
intersector (``trimesh.ray.ray_triangle``, not the embree one).

trimesh's narrow phase (``ray_triangle_id``: the ray–plane point of each candidate face, then
its barycentric coordinates, inside when all lie in [−1e-13, 1 + 1e-13]) is used as it is; its
broad phase wants an ``rtree`` index, which is not installed, so a stand-in (:class:`_Candidates`)
hands it, per ray, the faces whose bounding ball the ray's line meets — a superset of the faces
the ray can hit, so the answer is trimesh's.  Hit/miss must agree on every ray the reference
judges and the depths to 1e-12 (relative, floored at 1); the rays the reference flags
(``Case.judged_mask``: near-tangent, e.g. touching a silhouette edge) are counted and few.  The
cameras at scale are checked too: the 256² one in full, the 1024² one on every 64th ray.
"""

from __future__ import annotations

import numpy as np
import pytest

from reference.cases import LARGE_SIZES, get_case
from reference.mesh_cases import MESH_CASE_IDS

#: cameras up to 256² are checked on every ray; larger ones on every STRIDE-th
AT_MOST, STRIDE = 65536, 64


class _Candidates:
    """A stand-in for trimesh's rtree index: ``bounds`` of the mesh, and ``intersection(box)``
    returning, at the i-th call, the candidate faces of ray i (trimesh queries rays in order)."""

    def __init__(self, bounds, per_ray):
        self.bounds = np.asarray(bounds, np.float64).ravel()
        self._it = iter(per_ray)

    def intersection(self, _box):
        return next(self._it)


def _ball_candidates(V, F, o, d, chunk=512):
    """Per ray, the faces whose bounding ball (centroid, farthest vertex, padded) the line meets."""
    tri = V[F]
    c = tri.mean(axis=1)
    r = np.max(np.linalg.norm(tri - c[:, None], axis=2), axis=1) * (1 + 1e-9) + 1e-12 * np.ptp(V, axis=0).max()
    out = []
    for s in range(0, o.shape[0], chunk):
        w = c[None] - o[s : s + chunk, None]  # (r, f, 3)
        along = np.einsum("rfk,rk->rf", w, d[s : s + chunk])
        perp2 = np.einsum("rfk,rfk->rf", w, w) - along**2
        near = perp2 <= (r**2)[None] * (1 + 1e-9) + 1e-300
        out.extend(np.flatnonzero(row) for row in near)
    return out


def trimesh_first_hits(mesh, o, d, t_min, t_max):
    """First hit in (t_min, t_max] per ray by trimesh's ray–triangle narrow phase (inf: miss)."""
    import trimesh
    from trimesh.ray.ray_triangle import ray_triangle_id

    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    tree = _Candidates(tm.bounds, _ball_candidates(mesh.vertices, mesh.faces, o, d))
    _, ray, loc = ray_triangle_id(tm.triangles, o, d, triangles_normal=tm.face_normals, tree=tree, multiple_hits=True)
    t = np.einsum("ij,ij->i", loc - o[ray], d[ray]) if len(ray) else np.zeros(0)
    keep = (t > t_min) & (t <= t_max)
    first = np.full(o.shape[0], np.inf)
    np.minimum.at(first, ray[keep], t[keep])
    return first


def _large(cid: str) -> bool:
    """A camera at scale (256², 1024²): the slow tier checks it (a quarter of a minute each)."""
    return cid.endswith(tuple(f".{n}x{n}" for n in LARGE_SIZES))


@pytest.mark.parametrize("cid", [pytest.param(c, marks=pytest.mark.slow) if _large(c) else c for c in MESH_CASE_IDS])
def test_mesh_case_agrees_with_trimesh(cid):
    case = get_case(cid)
    idx = np.arange(case.n_rays)
    if case.n_rays > AT_MOST:
        idx = idx[::STRIDE]
    o, d = case.origins[idx], case.directions[idx]
    if idx.size == case.n_rays:
        ref, judged = case.exact_t, case.judged_mask
    else:  # the reference on the subsample only (its answers are per ray): the same functions Case uses
        from reference.depthbound import depth_bounds

        ref = case.scene.first_hit(o, d, case.t_min)
        ref = np.where(ref <= case.t_max, ref, np.inf)
        judged = np.isfinite(depth_bounds(case.scene, o, d, ref))
    tt = trimesh_first_hits(case.scene, o, d, case.t_min, case.t_max)
    # flagged rays: counted, few
    assert (~judged).sum() <= max(2, 0.01 * idx.size), f"{cid}: {(~judged).sum()} rays flagged"
    hit, thit = np.isfinite(ref), np.isfinite(tt)
    differ = np.flatnonzero(judged & (hit != thit))
    assert differ.size == 0, f"{cid}: hit/miss differs on {differ.size} judged rays, e.g. {idx[differ[:5]]}"
    both = judged & hit
    dt = np.abs(ref[both] - tt[both]) / np.maximum(np.abs(ref[both]), 1.0)
    assert dt.max(initial=0.0) <= 1e-12, f"{cid}: depth differs by {dt.max():.3g} (relative)"
    assert both.sum() > 0.1 * idx.size
