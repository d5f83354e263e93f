"""Cases on the stored meshes (:mod:`reference.make_meshes`), for the catalog to register.

:func:`mesh_cases` returns :class:`reference.cases.Case` objects with ids ``mesh.<shape>.<family>``
and tags from :func:`reference.cases._scene_tags` (``mesh``, ``sdf``, ``lipschitz``) plus the
family's.  Their exact first hits are the float64 ray–triangle hits of :class:`MeshSDF`.
"""

from __future__ import annotations

import functools

import numpy as np

from . import rays as _rays
from .cases import LARGE_SIZES, Case, _cam, large_tags, make_case, register_each
from .mesh import MeshSDF


@functools.cache
def stored_mesh(name: str) -> MeshSDF:
    """The stored mesh ``name``, one instance per process (its trees are built once)."""
    return MeshSDF.load(name)


def edge_grazing_rays(mesh: MeshSDF, n: int, offset: float, seed: int):
    """Rays passing ±``offset`` · size from random convex edges of ``mesh``, perpendicular to
    the edge and to the edge's mean normal b = (n₁ + n₂)/|n₁ + n₂|: the ray through
    e + s·offset·size·b (e a random point of the edge, s = +1 for even rays: just outside the
    edge, −1: just inside it), starting twice the bounding radius before it (outside the mesh)."""
    import trimesh

    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False, validate=False)
    adj, edges = tm.face_adjacency, tm.face_adjacency_edges
    n1, n2 = mesh.face_normals[adj[:, 0]], mesh.face_normals[adj[:, 1]]
    convex = tm.face_adjacency_convex & (np.einsum("ij,ij->i", n1, n2) < 1 - 1e-9)  # a real crease
    rng = np.random.default_rng(seed)
    pick = rng.choice(np.flatnonzero(convex), n)
    p, q = mesh.vertices[edges[pick, 0]], mesh.vertices[edges[pick, 1]]
    e = p + rng.uniform(0.2, 0.8, n)[:, None] * (q - p)
    b = _rays.normalize(n1[pick] + n2[pick])
    d = _rays.normalize(np.cross(q - p, b)) * rng.choice([-1.0, 1.0], n)[:, None]
    s = np.where(np.arange(n) % 2 == 0, 1.0, -1.0)
    x = e + (s * offset * mesh.size)[:, None] * b
    return x - 2.0 * mesh.bounding_sphere()[1] * d, d


def _case(case_id, scene, o, d, tags, description) -> Case:
    return make_case(case_id, scene, o, d, tags=tags, description=description)


def _fin_thin():
    """Rays crossing the 0.008-thick wall: along ±x (through its thickness) and oblique."""
    rng = np.random.default_rng(101)
    n = 256
    y, z = rng.uniform(-0.38, 0.38, n), rng.uniform(-0.05, 0.48, n)
    sx = np.where(np.arange(n) % 2 == 0, 1.0, -1.0)
    d = np.stack([sx, rng.uniform(-0.3, 0.3, n), rng.uniform(-0.3, 0.3, n)], axis=1)
    d[: n // 4, 1:] = 0.0  # a quarter exactly along the wall's normal
    d = _rays.normalize(d)
    x = np.stack([np.zeros(n), y, z], axis=1)
    return x - 2.0 * d, d


def _fin_parallel():
    """Rays parallel to the wall's faces x = ±0.004, 1e-9 inside or outside their plane."""
    rng = np.random.default_rng(102)
    n = 256
    side = rng.choice([-1.0, 1.0], n)
    off = np.where(np.arange(n) % 2 == 0, 1e-9, -1e-9)  # + outside the wall, − inside it
    x0 = side * (0.004 + off)
    horizontal = np.arange(n) % 4 < 2
    o = np.where(horizontal[:, None],
                 np.stack([x0, np.full(n, -2.0), rng.uniform(-0.05, 0.48, n)], axis=1),
                 np.stack([x0, rng.uniform(-0.38, 0.38, n), np.full(n, 2.0)], axis=1))
    d = np.where(horizontal[:, None], np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, -1.0]))
    return o, d


def _blob_inside():
    o, d = _rays.in_ball(256, 0.5, seed=103)
    return o, d


#: the structural tags of a mesh case's scene (:func:`reference.cases.case_tags` of a :class:`MeshSDF`)
MESH_SCENE_TAGS = ("mesh", "sdf", "lipschitz")


def _mesh_specs() -> dict:
    """id → (mesh name, rays(mesh) → (origins, directions), the case's own tags, description)
    of every mesh case, in catalog order."""
    specs = {
        "mesh.torus.camera.32x32": ("torus", lambda m: _cam(32, eye=(0.0, -2.5, 1.8)), ("camera",),
                                    "torus mesh (R = 1, r = 0.25, 4096 faces) seen obliquely by a 32×32 camera"),
        # the quick suite's mesh: the same view at 16×16 (each φ call is a host call into libigl,
        # the costliest φ per point of the catalog)
        "mesh.torus.camera.16x16": ("torus", lambda m: _cam(16, eye=(0.0, -2.5, 1.8)), ("camera", "quick"),
                                    "torus mesh (R = 1, r = 0.25, 4096 faces) seen obliquely by a 16×16 camera"),
        "mesh.fin.camera.32x32": ("fin", lambda m: _cam(32, eye=(1.6, -1.9, 1.5)), ("camera", "thin"),
                                  "a block with a 0.008-thick wall (sharp edges), 32×32 camera"),
        "mesh.fin.thin": ("fin", lambda m: _fin_thin(), ("thin", "wall", "stability"),
                          "rays through the 0.008-thick wall, a quarter along its normal, the rest oblique"),
        "mesh.fin.parallel": ("fin", lambda m: _fin_parallel(), ("parallel", "grazing"),
                              "rays parallel to the wall's faces, 1e-9 outside (miss the wall) or inside (hit its end "
                              "or top)"),
        "mesh.blob.camera.32x32": ("blob", lambda m: _cam(32, fov=50.0), ("camera",),
                                   "a seeded wavy sphere (5120 faces), 32×32 camera"),
        "mesh.blob.inside": ("blob", lambda m: _blob_inside(), ("inside",),
                             "origins inside the blob (|o| ≤ 0.5), random directions: the first hit is the exit"),
    }
    for k in (3, 6, 9):
        for name in ("torus", "fin", "blob"):
            # the fin's (68 faces) 1e-6 edge rays stand for the family in the stability matrix
            stab = ("stability",) if (name, k) == ("fin", 6) else ()
            specs[f"mesh.{name}.grazing.1e-{k}"] = (
                name, lambda m, k=k: edge_grazing_rays(m, 256, 10.0**-k, seed=110 + k), ("grazing", "edge") + stab,
                f"rays perpendicular to random convex edges passing 1e-{k} × size outside (even rays) or inside "
                "(odd rays) the edge")
    for n in LARGE_SIZES:
        specs[f"mesh.torus.camera.{n}x{n}"] = ("torus", lambda m, n=n: _cam(n, eye=(0.0, -2.5, 1.8)), large_tags(n),
                                               f"torus mesh (R = 1, r = 0.25, 4096 faces) seen obliquely by a {n}×{n} "
                                               "camera")
    return specs


_MESH_SPECS = _mesh_specs()
#: the ids :func:`mesh_case` builds, registered in the catalog without building them (tags
#: declared: a suite chosen by tag loads no mesh it does not run)
MESH_CASE_IDS = tuple(_MESH_SPECS)


def mesh_case(case_id: str) -> Case:
    """The mesh case ``case_id`` (one of :data:`MESH_CASE_IDS`), on its stored mesh."""
    name, rays, tags, description = _MESH_SPECS[case_id]
    mesh = stored_mesh(name)
    return _case(case_id, mesh, *rays(mesh), tags, description)


def mesh_cases() -> list[Case]:
    """Every mesh case (:data:`MESH_CASE_IDS`): the catalog's, where the mesh extra registered them."""
    from .cases import case_ids, get_case

    known = set(case_ids())
    return [get_case(cid) if cid in known else mesh_case(cid) for cid in MESH_CASE_IDS]


def _register() -> None:
    # the mesh scenes need libigl and trimesh (the ``mesh`` extra); without them the catalog has no mesh cases
    import importlib.util

    if all(importlib.util.find_spec(m) is not None for m in ("igl", "trimesh")):
        register_each({cid: MESH_SCENE_TAGS + spec[2] for cid, spec in _MESH_SPECS.items()}, mesh_case)


_register()
