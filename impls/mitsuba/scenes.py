"""isobench scenes as Mitsuba 3 scenes: a grid SDF as an ``sdfgrid`` shape, a mesh as a ``Mesh``.

Grid (:class:`reference.grid.GridSDF`).  Mitsuba's ``sdfgrid`` maps its sample tensor, packed
[z, y, x, channel], over the unit cube of its object space with samples at the vertices
(voxel size 1/(n − 1) per axis, ``src/shapes/sdfgrid.cpp``) and interpolates trilinearly, as
:class:`GridSDF` does over its box B = [lo, hi]: so the tensor is ``values`` transposed to
(z, y, x) with a channel axis, in float32 (the shape stores its grid in single precision), and
``to_world`` = translate(lo) · scale(hi − lo).  Mitsuba intersects the shape inside B only; a
grid whose surface leaves B (not :attr:`GridSDF.closed`) is declined.

Mesh (:class:`reference.mesh.MeshSDF`).  Vertices (float32) and faces as a Mitsuba ``Mesh``
built from Python (``mi.Mesh`` with its ``vertex_positions`` and ``faces`` parameters).

Both are put in a scene of their own (``mi.load_dict``), whose ray intersection is Mitsuba's:
on ``llvm_*`` variants Embree's BVH (the SDF grid a user primitive per non-empty voxel), on
``cuda_*`` variants OptiX.
"""

from __future__ import annotations

import numpy as np


def decline_reason(scene) -> str | None:
    """Why Mitsuba has no shape for ``scene``, or None."""
    from reference.grid import GridSDF
    from reference.mesh import MeshSDF

    if isinstance(scene, MeshSDF):
        return None
    if isinstance(scene, GridSDF):
        if not scene.closed:
            return ("mitsuba's sdfgrid intersects inside the grid's box only; this grid's surface leaves the box "
                    f"(a boundary sample is {scene.boundary_min:.3g} ≤ 0)")
        return None
    return (f"mitsuba's ray queries take triangle meshes (Mesh) and SDF grids (sdfgrid); {type(scene).__name__} is "
            "neither")


def build(scene):
    """A Mitsuba scene holding ``scene`` as its one shape (the current variant's types)."""
    import mitsuba as mi

    from reference.grid import GridSDF

    if isinstance(scene, GridSDF):
        data = np.ascontiguousarray(np.transpose(scene.values, (2, 1, 0))[..., None], np.float32)
        to_world = mi.ScalarTransform4f().translate(scene.lo.tolist()).scale((scene.hi - scene.lo).tolist())
        shape = {"type": "sdfgrid", "grid": mi.TensorXf(data), "to_world": to_world}
        return mi.load_dict({"type": "scene", "shape": shape})
    V = np.asarray(scene.vertices, np.float32)
    F = np.asarray(scene.faces, np.uint32)
    mesh = mi.Mesh("isobench_mesh", V.shape[0], F.shape[0], has_vertex_normals=False, has_vertex_texcoords=False)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(V.reshape(-1))
    params["faces"] = mi.UInt32(F.reshape(-1))
    params.update()
    return mi.load_dict({"type": "scene", "shape": mesh})
