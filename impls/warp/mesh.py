"""First hits on triangle meshes with Warp's BVH ray query (``wp.mesh_query_ray``).

The outputs are those of the engine backends (:mod:`impls.engine`): the depth and the hit face's
normal as the query returns it (``MeshQueryRay.normal``), normalised in float64.  Warp stores a mesh's points as ``vec3`` (float32) and computes the query in float32: the
origin, direction, depth and hit test are float32, the answer the engine's own.  The query
returns the nearest face hit with 0 ≤ t ≤ ``max_t``; the ray starts at o + t_min·d (computed in
float64, then rounded) and t_min is added back, so the search covers [t_min, t_max] as every
method's does.  A ray with no hit is MISS (t = inf); rays that :func:`impls.base.check_rays`
marked invalid (a NaN direction) are BAD_INPUT before any query.
"""

from __future__ import annotations

import numpy as np

from ..protocol import Status

#: the largest float32: the query's max_t for t_max = inf
F32_MAX = float(np.finfo(np.float32).max)

_KERNEL = None


def _kernel():
    global _KERNEL
    if _KERNEL is None:
        import warp as wp

        @wp.kernel
        def first_hit(mesh: wp.uint64, O: wp.array(dtype=wp.vec3), D: wp.array(dtype=wp.vec3), max_t: float,
                      T: wp.array(dtype=float), N: wp.array(dtype=wp.vec3), hit: wp.array(dtype=wp.int32)):
            i = wp.tid()
            q = wp.mesh_query_ray(mesh, O[i], D[i], max_t)
            if q.result:
                T[i] = q.t
                N[i] = q.normal
                hit[i] = 1
            else:
                T[i] = 0.0  # (no uninitialised value for the host to read)
                N[i] = wp.vec3(0.0, 0.0, 0.0)
                hit[i] = 0

        _KERNEL = first_hit
    return _KERNEL


class WarpMesh:
    """A :class:`reference.mesh.MeshSDF` as a ``wp.Mesh`` (its BVH built once) on ``device``."""

    def __init__(self, mesh, device: str):
        import warp as wp

        self.device = device
        self.points = wp.array(np.asarray(mesh.vertices, np.float32), dtype=wp.vec3, device=device)
        self.indices = wp.array(np.asarray(mesh.faces, np.int32).reshape(-1), dtype=wp.int32, device=device)
        self.mesh = wp.Mesh(points=self.points, indices=self.indices)

    def first_hit(self, o: np.ndarray, d: np.ndarray, t_min: float, t_max: float) -> dict:
        """``{t, status, iterations, evals}`` of the first hit in [t_min, t_max] per ray (module
        docstring); counts are 0 (the engine evaluates no field)."""
        import warp as wp

        n = o.shape[0]
        o64, d64 = np.asarray(o, np.float64), np.asarray(d, np.float64)
        bad = ~np.all(np.isfinite(o64) & np.isfinite(d64), axis=1)
        start = np.where(bad[:, None], 0.0, o64 + t_min * d64).astype(np.float32)
        dirs = np.where(bad[:, None], 0.0, d64).astype(np.float32)
        span = t_max - t_min
        max_t = F32_MAX if not np.isfinite(span) else float(min(span, F32_MAX))
        O = wp.array(start, dtype=wp.vec3, device=self.device)
        D = wp.array(dirs, dtype=wp.vec3, device=self.device)
        T = wp.empty(n, dtype=float, device=self.device)
        N = wp.empty(n, dtype=wp.vec3, device=self.device)
        H = wp.empty(n, dtype=wp.int32, device=self.device)
        wp.launch(_kernel(), dim=n, inputs=[self.mesh.id, O, D, max_t, T, N, H], device=self.device)
        # Array.numpy() copies back on the launch's stream, so on a GPU it waits for the kernel
        hit, t, nrm = H.numpy().astype(bool), T.numpy(), N.numpy().astype(np.float64)
        t_out = np.where(hit, t.astype(np.float64) + t_min, np.inf)
        status = np.where(hit, Status.CONVERGED, Status.MISS).astype(np.int32)
        t_out[bad], status[bad] = np.nan, Status.BAD_INPUT
        nrm = unit_normals(nrm, hit & ~bad)
        zeros = np.zeros(n, np.int32)
        return {"t": t_out.astype(o.dtype), "status": status, "iterations": zeros, "evals": zeros.copy(),
                "normal": nrm}


def unit_normals(n: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """The engine's normals (n, 3) normalised in float64, NaN where ``valid`` is False (a MISS, a
    bad ray: impls/engine.py's convention for the output ``normal``)."""
    out = np.full(n.shape, np.nan)
    v = n[valid]
    with np.errstate(invalid="ignore", divide="ignore"):
        out[valid] = v / np.linalg.norm(v, axis=1, keepdims=True)
    return out
