"""A closed triangle mesh as a scene node: its exact signed distance and exact ray hits.

:class:`MeshSDF` holds float64 vertices V (n, 3) and faces F (m, 3) of a closed, watertight,
consistently oriented (outward) triangle mesh M and evaluates

    φ(x) = s(x) · min_{y ∈ M} |x − y|,     s(x) = −1 inside (winding number 1), +1 outside,

the exact signed distance to the piecewise-linear surface (L = 1).  Its gradient off the
surface and off the medial axis is ∇φ(x) = (x − c)/φ(x) with c the closest point (a unit
vector pointing away from the surface outside, towards it inside); on the surface it is the
outward unit face normal of the face containing x.  Curvature is zero on faces and undefined on
edges, so none is offered.  The mesh has no differentiable parameters.

Validation on construction (a mesh that is not a solid's boundary is a ValueError naming what
is wrong and the fix): finite vertices, integer faces indexing them, no zero-area face,
watertight (every edge shared by exactly two faces: ``trimesh.Trimesh.is_watertight``),
consistently oriented (``is_winding_consistent``), outward (positive volume), no two faces
crossing (libigl's exact ``copyleft.cgal.remesh_self_intersections`` in detect-only mode), and
every shell with winding number 1 just inside and 0 just outside (no shell nested in one of the
same orientation; a cavity faces inward).  A mesh passing these is the boundary of the solid
{w = 1}, w the winding number, which is what the sign of φ below assumes.

How each answer is computed (float64):

* Unsigned distance, closest point c and closest face: libigl's AABB tree
  (``igl.AABB.squared_distance``; Jacobson et al., libigl, https://libigl.github.io), built
  once per node.
* Sign: where x − c is parallel to the closest face's normal n_f (|cos| ≥ 1 − 1e-6), the sign
  of ⟨x − c, n_f⟩: the open segment (x, c) meets no surface (c is the closest point), so x lies
  on the side of the face it faces.  Elsewhere (closest point on an edge or a vertex) the sign
  of ⟨x − c, n⟩ with n the angle-weighted pseudonormal of that edge or vertex (Bærentzen &
  Aanæs, "Signed distance computation using the angle weighted pseudonormal", IEEE TVCG 2005:
  exact for a closed, consistently oriented mesh), the feature read off c's barycentric
  coordinates; hand-written and vectorised because ``igl.pseudonormal_test`` takes one point a
  call.  Where that product is within 1e-3 of perpendicular (rounding could decide it), the
  exact generalized winding number w(x) − ½ (Jacobson, Kavan & Sorkine-Hornung, SIGGRAPH 2013)
  from ``igl.signed_distance(..., SIGNED_DISTANCE_TYPE_WINDING_NUMBER)`` decides; that call
  rebuilds its trees (tens of milliseconds on a 4096-face mesh), so it serves only those few
  points.  ``igl.fast_winding_number`` is not used: its far-field approximation flipped the
  sign of points within ~5e-3 of a 20k-face sphere.  The parallel test is skipped for meshes
  with a fold sharper than 1e-3 rad (adjacent faces with n₁·n₂ < −(1 − 1e-6)), whose inner
  wedge could contain a direction near +n_f; there the pseudonormal of a fold's edge is
  undefined (n₁ + n₂ ≈ 0) and the winding number decides.
* Ray hits: hand-written, because libigl's ``AABB.intersect_ray_first`` and
  ``ray_mesh_intersect`` compute in single precision (errors ~1e-7 at unit scale, and no hits
  at all on a sphere of radius 1e-3); trimesh's intersector needs rtree/embree, which are not
  installed.  A two-level bound (faces sorted along a Morton curve of their centroids, blocks
  of 16 with a padded bounding ball) culls (ray, face) pairs; the survivors take the plane
  intersection t = ⟨n, a − o⟩/⟨n, d⟩ and the signed-volume inside test
  e_pq = ⟨(p − o) × (q − o), d⟩ on each edge pq (Plücker coordinates; a hit when the three
  edge values of a face are all ≥ 0 or all ≤ 0).  Each edge's value is computed once, with
  its endpoints in increasing vertex order, and negated for the face that uses the edge the
  other way round, so the two faces of an edge see the same number: a ray through an edge
  hits at least one of them (no cracks; Woop, Benthin & Wald, "Watertight ray/triangle
  intersection", JCGT 2013, make the same argument).  The first hit counts a ray touching a
  silhouette edge or vertex as a hit (like sphere and torus count a tangent ray).
* Ray intervals: the hits clustered (|Δt| ≤ 1e-12 (|t| + size)), and the sign of φ at the
  midpoints between consecutive clusters says which gaps are inside; a touch bounds no
  interval (as in CSG).

Backends: φ evaluates on numpy, torch and jax points through a host call into libigl (numpy,
float64; results are cast back to the points' dtype and device).  torch: a
``torch.autograd.Function`` whose backward and forward-mode ``jvp`` use ∇φ from the same host
call (``torch.autograd.grad`` and ``torch.func.jvp`` work); its backward raises a RuntimeError under ``create_graph=True``,
so a second derivative fails loudly instead of returning a zero Hessian.  jax: a host call under ``jax.custom_jvp`` with tangent
⟨∇φ, dx⟩ (``jax.jit``, ``jax.grad``, ``jax.jvp`` work; a second derivative raises, since the
call returning ∇φ has no derivative); on the CPU an XLA FFI custom call named by the mesh data's
SHA-256, so that jax's persistent compilation cache keeps the programs (:mod:`reference.jax_host_call`;
``jax.pure_callback`` programs are never cached), elsewhere ``jax.pure_callback``.  Cost: the host call into libigl's closest-point
query dominates on every backend (the torch and jax bridges add nothing measurable over numpy),
so mesh cases are the costliest per point of the catalog.  A call with a point the pseudonormal
leaves undecided also pays the winding-number call's tree build (rare).
"""

from __future__ import annotations

import functools
import hashlib
from pathlib import Path

import numpy as np

from .scene import Field, SceneInfo, _points, unit

DATA = Path(__file__).with_name("data") / "meshes"

_PARALLEL_COS = 1.0 - 1e-6
_PSEUDO_COS = 1e-3  # |cos(x − c, pseudonormal)| at or below which the exact winding number decides
_BARY_ZERO = 1e-9  # a barycentric coordinate of the closest point at or below this is on an edge
_BLOCK = 16


def _ball_near(w: np.ndarray, u: np.ndarray, radius: np.ndarray, speed: np.ndarray, t_min: float) -> np.ndarray:
    """Where a ray may meet a ball at t > t_min: its line passes within the radius of the centre
    (w = centre − origin, u the unit direction) and the ball's far end lies past t_min (in t,
    distance / speed).  Padded against the rounding of |w⊥| (relative to |w|) and of the ball
    itself; broadcasts over leading axes."""
    wd = np.einsum("...k,...k->...", w, u)
    perp = np.linalg.norm(w - wd[..., None] * u, axis=-1)
    slack = radius + 1e-9 * (np.linalg.norm(w, axis=-1) + radius)
    with np.errstate(invalid="ignore", divide="ignore"):
        return (perp <= slack) & ((wd + slack) / speed > t_min)


def _check_solid_boundary(V: np.ndarray, F: np.ndarray, tm) -> None:
    """Refuse a watertight, consistently oriented mesh that is still not the boundary of a solid.

    1. Self-intersection: no two faces may meet except in the edge or vertex they share.  Decided
       by libigl's ``copyleft.cgal.remesh_self_intersections(..., detect_only=True)`` (CGAL's exact
       predicates, so no tolerance; Zhou, Grinspun, Zorin & Jacobson, "Mesh arrangements for solid
       geometry", SIGGRAPH 2016).  Two overlapping closed shells in one face list pass the
       watertight and winding checks, yet the unsigned distance then ignores the buried faces'
       shell, and a point inside both shells can read φ > 0.
    2. Nesting: every connected shell must have winding number 1 just inside and 0 just outside
       (libigl's exact generalized winding number, Jacobson, Kavan & Sorkine-Hornung 2013, at one
       face of each shell, offset by 1e-7 of the mesh's size along ∓ its normal).  A shell inside
       another with the same (outward) orientation has winding number 2 inside: the solid is not
       the set {w = 1} the sign of φ assumes; a cavity's shell must face inward."""
    import igl

    try:
        from igl.copyleft import cgal
    except ImportError:  # pragma: no cover - the mesh extra installs libigl with its CGAL module
        cgal = None
    if cgal is not None:
        pairs = cgal.remesh_self_intersections(V, np.ascontiguousarray(F, np.int64), detect_only=True,
                                                first_only=True)[2]
        if len(pairs):
            a, b = (int(i) for i in pairs[0])
            raise ValueError(
                f"faces intersect each other (e.g. faces {a} and {b} cross away from any shared edge): the mesh "
                "is not the boundary of a solid (two overlapping shells in one face list, or a surface through "
                "itself). Merge overlapping parts with a boolean union (igl.copyleft.cgal.mesh_boolean(VA, FA, "
                "VB, FB, 'union') or trimesh.boolean.union) or resolve the crossings "
                "(igl.copyleft.cgal.remesh_self_intersections)")
    labels = _face_components(tm)
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    area = np.linalg.norm(n, axis=1)
    h = 1e-7 * float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))
    probes, which = [], []
    for k in np.unique(labels):
        f = int(np.flatnonzero(labels == k)[np.argmax(area[labels == k])])  # its largest face
        c, u = V[F[f]].mean(axis=0), n[f] / area[f]
        probes += [c - h * u, c + h * u]
        which.append((int(k), f))
    w = np.asarray(igl.winding_number(V, F, np.asarray(probes)), np.float64).reshape(-1, 2)
    bad = [(k, f, wi) for (k, f), wi in zip(which, w) if not (abs(wi[0] - 1) < 0.5 and abs(wi[1]) < 0.5)]
    if bad:
        k, f, wi = bad[0]
        raise ValueError(
            f"faces form {len(which)} shells and shell {k} (e.g. face {f}) has winding number {wi[0]:.0f} just "
            f"inside and {wi[1]:.0f} just outside (a solid's boundary has 1 and 0): it is nested in another shell "
            "with the same orientation. Reverse a cavity's faces (faces[:, ::-1] on that shell) so it faces inward, "
            "or merge the shells with a boolean union")


def _face_components(tm) -> np.ndarray:
    """Connected component (by shared edges) of each face."""
    import trimesh

    labels = np.zeros(len(tm.faces), np.int64)
    for k, comp in enumerate(trimesh.graph.connected_components(tm.face_adjacency, nodes=np.arange(len(tm.faces)))):
        labels[np.asarray(comp, np.int64)] = k
    return labels


def _morton_order(p: np.ndarray) -> np.ndarray:
    """Indices sorting points ``p`` (n, 3) along a 10-bit-per-axis Morton (Z-order) curve."""
    lo, hi = p.min(axis=0), p.max(axis=0)
    q = np.clip(((p - lo) / np.where(hi > lo, hi - lo, 1.0) * 1023).astype(np.int64), 0, 1023)
    code = np.zeros(p.shape[0], np.int64)
    for bit in range(10):
        for axis in range(3):
            code |= ((q[:, axis] >> bit) & 1) << (3 * bit + axis)
    return np.argsort(code, kind="stable")


#: a face whose height is at most this times its longest edge is degenerate (MeshSDF refuses it):
#: collinear to float64 rounding (the cross product's own rounding is a few ε · longest²)
_DEGENERATE_HEIGHT = 16 * float(np.finfo(np.float64).eps)


class MeshSDF(Field):
    """Signed distance to a closed, watertight, outward-oriented triangle mesh (see the module).

    ``vertices`` (n, 3) float, ``faces`` (m, 3) integer indices into them; ``name`` labels the
    mesh in specs and reports.  φ < 0 inside, exact SDF, L = 1, exact hits and normals.
    """

    kind = "mesh"

    def __init__(self, vertices, faces, name: str = "mesh"):
        V = np.asarray(vertices, dtype=np.float64)
        if V.ndim != 2 or V.shape[1] != 3 or V.shape[0] < 4 or not np.all(np.isfinite(V)):
            raise ValueError(f"vertices must be a finite float array of shape (n ≥ 4, 3), got shape {V.shape}")
        F0 = np.asarray(faces)
        if F0.ndim != 2 or F0.shape[1] != 3 or F0.shape[0] < 4 or F0.dtype.kind not in "iu":
            raise ValueError(f"faces must be an integer array of shape (m ≥ 4, 3), got shape {F0.shape} dtype {F0.dtype}")
        if F0.min() < 0 or F0.max() >= V.shape[0]:
            raise ValueError(f"faces index vertices 0…{V.shape[0] - 1}, got indices {F0.min()}…{F0.max()}")
        F = F0.astype(np.int64)
        import trimesh

        tm = trimesh.Trimesh(V, F, process=False, validate=False)
        n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
        area = np.linalg.norm(n, axis=1)  # twice the face's area: |cross| = longest edge · height
        e = V[F] - V[F[:, [1, 2, 0]]]
        longest2 = np.max(np.einsum("fij,fij->fi", e, e), axis=1)
        # collinear to rounding counts as zero area: the cross product of a face whose height is
        # within rounding of 0 is rounding, not 0, and such a face made the rounding model
        # (rounding_gain, ∝ longest/height ~ 1e16) flag every hit of the mesh
        flat = area <= _DEGENERATE_HEIGHT * longest2
        if np.any(flat):
            raise ValueError(f"faces has {int(np.sum(flat))} degenerate triangles (zero area, or collinear to rounding: "
                             f"height ≤ {_DEGENERATE_HEIGHT:.0e} × longest edge), e.g. face {int(np.argmax(flat))}; "
                             "remove them and merge what they split (trimesh: mesh.update_faces("
                             "mesh.nondegenerate_faces()); mesh.merge_vertices()), then check it is still watertight")
        if not tm.is_watertight:
            raise ValueError("faces does not form a watertight mesh (some edge is not shared by exactly two faces): "
                             "if its vertices are not merged (a triangle soup, as STL files load), merge them "
                             "(trimesh: mesh.merge_vertices(), or trimesh.Trimesh(..., process=True)); otherwise close "
                             "the holes (e.g. trimesh.repair.fill_holes)")
        if not tm.is_winding_consistent:
            raise ValueError("faces is not consistently oriented (two faces traverse a shared edge the same way); "
                             "fix with trimesh.repair.fix_winding")
        # (a volume within rounding of 0 is no volume: the faces' signed contributions cancel)
        vol, tiny = float(tm.volume), 1e-9 * float(np.max(np.ptp(V, axis=0))) ** 3
        if vol < -tiny:
            raise ValueError("faces is oriented inward (negative volume); reverse each face's vertex order "
                             "(faces[:, ::-1]) so normals point outward")
        if abs(vol) <= tiny:
            raise ValueError("faces encloses no volume (0: e.g. every face twice, once each way, as filling the "
                             "holes of an unmerged triangle soup makes); merge its vertices instead "
                             "(trimesh: mesh.merge_vertices())")
        _check_solid_boundary(V, F, tm)
        self.vertices = V
        self.faces = F
        self.name = str(name)
        self.vertices.setflags(write=False)
        self.faces.setflags(write=False)
        self.face_normals = n / area[:, None]
        adj = tm.face_adjacency
        fold = np.einsum("ij,ij->i", self.face_normals[adj[:, 0]], self.face_normals[adj[:, 1]])
        self._parallel_sign_ok = bool(np.all(fold >= -_PARALLEL_COS))
        lo, hi = V.min(axis=0), V.max(axis=0)
        self._centre = 0.5 * (lo + hi)
        self._radius = float(np.max(np.linalg.norm(V - self._centre, axis=1))) * (1 + 1e-12)
        self.size = float(np.linalg.norm(hi - lo))
        # libigl's closest point on a skinny triangle rounds like eps · (longest edge)/(height)
        # times the coordinates: the surface tolerance scales with the worst such ratio
        self._skinny = float(np.max(longest2 / area))  # longest/height

    @classmethod
    def load(cls, name: str) -> "MeshSDF":
        """The stored mesh ``reference/data/meshes/<name>.npz`` (made by :mod:`reference.make_meshes`)."""
        path = DATA / f"{name}.npz"
        if not path.exists():
            raise ValueError(f"mesh {name!r} not found at {path}; run `python -m reference.make_meshes`")
        with np.load(path) as f:
            return cls(f["vertices"], f["faces"], name=name)

    # -- structure -------------------------------------------------------------------------
    @property
    def info(self) -> SceneInfo:
        return SceneInfo(exact_sdf=True, lipschitz=1.0, distance_bound=True, smooth=False, exact_hits=True,
                         exact_normals=True, exact_curvature=False, exact_hit_param_grad=False)

    def _rebuild(self, own, children):
        return self

    def _static_spec(self) -> dict:
        h = hashlib.sha256(np.ascontiguousarray(self.vertices).tobytes())
        h.update(np.ascontiguousarray(self.faces).tobytes())
        return {"name": self.name, "n_vertices": int(self.vertices.shape[0]), "n_faces": int(self.faces.shape[0]),
                "data_sha256": h.hexdigest()}

    def bounding_sphere(self):
        return self._centre.copy(), self._radius

    @functools.cached_property
    def _tree(self):
        import igl

        tree = igl.AABB()
        tree.init(self.vertices, self.faces)
        return tree

    # -- φ on the host -------------------------------------------------------------------
    def closest(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(φ (n,), closest points c (n, 3), closest face (n,))`` at points ``x`` (n, 3), float64.
        A point with a NaN coordinate gets φ = NaN, one with an infinite coordinate φ = +inf (both
        with c = NaN, face −1), without a tree query: the masked drivers evaluate finished rays
        where their depth went (t = ∞ for a miss), and the AABB query visits every box for them."""
        import igl

        x = np.ascontiguousarray(_points(x))
        if x.shape[0] == 0:
            return np.zeros(0), np.zeros((0, 3)), np.zeros(0, np.int64)
        finite = np.isfinite(x).all(axis=1)
        if not finite.all():
            phi = np.where(np.isnan(x).any(axis=1), np.nan, np.inf)
            c = np.full_like(x, np.nan)
            face = np.full(x.shape[0], -1, np.int64)
            if finite.any():
                phi[finite], c[finite], face[finite] = self.closest(x[finite])
            return phi, c, face
        d2, face, c = self._tree.squared_distance(self.vertices, self.faces, x)
        dist = np.sqrt(d2)
        v = x - c
        dot = np.einsum("ij,ij->i", v, self.face_normals[face])
        if self._parallel_sign_ok:
            settled = np.abs(dot) >= _PARALLEL_COS * dist
        else:
            settled = np.zeros(x.shape[0], bool)
        sign = np.where(dot < 0, -1.0, 1.0)
        rest = np.flatnonzero(~settled)
        if rest.size:
            pdot = self._pseudonormal_dot(v[rest], c[rest], face[rest])
            sign[rest] = np.where(pdot < 0, -1.0, 1.0)
            # a pseudonormal nearly perpendicular to x − c (or a rounding-sized distance) decides
            # nothing robustly: those few points take the exact winding number
            unsure = rest[~(np.abs(pdot) > _PSEUDO_COS * dist[rest])]  # NaN (a fold's edge) too
            if unsure.size:
                s, *_ = igl.signed_distance(np.ascontiguousarray(x[unsure]), self.vertices, self.faces,
                                            igl.SIGNED_DISTANCE_TYPE_WINDING_NUMBER)
                sign[unsure] = np.where(s < 0, -1.0, 1.0)
        return sign * dist, c, face

    @functools.cached_property
    def _pseudonormals(self):
        """Edge pseudonormals (n_f + n_g, unit; #F × 3, one per face corner, for the edge opposite
        that corner) and angle-weighted vertex pseudonormals (#V × 3), Bærentzen & Aanæs 2005."""
        V, F, N = self.vertices, self.faces, self.face_normals
        m = F.shape[0]
        opp = np.stack([F[:, [1, 2]], F[:, [2, 0]], F[:, [0, 1]]], axis=1)  # (m, 3, 2): edge opposite corner i
        key = np.sort(opp, axis=2).reshape(-1, 2)
        _, edge_id = np.unique(key, axis=0, return_inverse=True)
        edge_id = edge_id.reshape(-1)
        en = np.zeros((int(edge_id.max()) + 1, 3))
        np.add.at(en, edge_id, np.repeat(N, 3, axis=0))
        en /= np.linalg.norm(en, axis=1, keepdims=True)  # a zero sum (a fold of π) gives NaN: never sure
        vn = np.zeros_like(V)
        for i in range(3):
            a, b, c = V[F[:, i]], V[F[:, (i + 1) % 3]], V[F[:, (i + 2) % 3]]
            u, w = b - a, c - a
            ang = np.arctan2(np.linalg.norm(np.cross(u, w), axis=1), np.einsum("ij,ij->i", u, w))
            np.add.at(vn, F[:, i], ang[:, None] * N)
        vn /= np.linalg.norm(vn, axis=1, keepdims=True)
        return en[edge_id].reshape(m, 3, 3), vn

    def _pseudonormal_dot(self, v, c, face):
        """⟨x − c, n⟩ with n the pseudonormal of the feature of face ``face`` that holds the closest
        point c (its interior: the face normal; an edge: the edge's; a vertex: the vertex's),
        whose sign is the sign of φ (Bærentzen & Aanæs, "Signed distance computation using the
        angle weighted pseudonormal", IEEE TVCG 2005).  The feature is read off c's barycentric
        coordinates, those ≤ 1e-9 counting as zero."""
        edge_n, vert_n = self._pseudonormals
        F, V = self.faces[face], self.vertices
        a, b, cc = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
        # barycentric coordinates by sub-triangle areas projected on the face normal
        n = self.face_normals[face]
        area = np.einsum("ij,ij->i", np.cross(b - a, cc - a), n)
        lam = np.stack([np.einsum("ij,ij->i", np.cross(b - c, cc - c), n),
                        np.einsum("ij,ij->i", np.cross(cc - c, a - c), n),
                        np.einsum("ij,ij->i", np.cross(a - c, b - c), n)], axis=1) / area[:, None]
        zero = lam <= _BARY_ZERO
        nz = zero.sum(axis=1)
        rows = np.arange(len(face))
        normal = n.copy()
        on_edge = nz == 1
        normal[on_edge] = edge_n[face[on_edge], np.argmax(zero[on_edge], axis=1)]
        on_vertex = nz >= 2
        corner = np.argmin(np.where(zero, np.inf, lam), axis=1)  # the one coordinate not ≈ 0
        normal[on_vertex] = vert_n[F[rows[on_vertex], corner[on_vertex]]]
        return np.einsum("ij,ij->i", v, normal)

    @property
    def rounding_gain(self) -> float:
        """The closest point's rounding is amplified by the skinniest face's aspect ratio
        (:meth:`_surface_tol`: 64ε (|x|∞ + size) · skinny): 4 · max(1, skinny) times the Lipschitz
        check's generic 16ε.  On the fin (skinny = 100) φ at a point a step lands on exactly reads
        up to −1.2e-13 at |x| ≈ 1.5, 550ε, where the generic slack allows 2.2e-14."""
        return 4.0 * max(1.0, self._skinny)

    def _surface_tol(self, x: np.ndarray) -> np.ndarray:
        """Distances below which x counts as on the surface (its normal is then the closest face's):
        the rounding of the closest point c, 64 eps (|x|∞ + size) times the skinniest face's
        (longest edge)/(height)."""
        return 64 * np.finfo(np.float64).eps * (np.max(np.abs(x), axis=1) + self.size) * max(1.0, self._skinny)

    def _jet(self, x):
        phi, c, face = self.closest(x)
        on = np.abs(phi) <= self._surface_tol(x)
        with np.errstate(invalid="ignore", divide="ignore"):
            g = (x - c) / np.where(on, 1.0, phi)[:, None]
        g[on] = self.face_normals[face[on]]
        return phi, unit(g), np.zeros((x.shape[0], 0))

    def closest_point_exact(self, x):
        return self.closest(_points(x))[1]

    def normal_exact(self, x):
        return self._jet(_points(x))[1]

    def _host(self, x: np.ndarray, with_grad: bool):
        """φ (and ∇φ) at points of any leading shape (…, 3), float64 numpy."""
        shape = x.shape[:-1]
        flat = np.ascontiguousarray(np.asarray(x, np.float64).reshape(-1, 3))
        if with_grad:
            phi, g, _ = self._jet(flat)
            return phi.reshape(shape), g.reshape(shape + (3,))
        return self.closest(flat)[0].reshape(shape)

    # -- φ in the caller's library -----------------------------------------------------------
    def _eval(self, x, xp, cursor):
        import array_api_compat

        if isinstance(x, np.ndarray):
            return self._host(x, False).astype(x.dtype, copy=False)
        if array_api_compat.is_torch_array(x):
            return _torch_phi(self, x)
        if array_api_compat.is_jax_array(x):
            return self._jax_phi(x)
        raise TypeError(f"MeshSDF evaluates numpy, torch or jax points, got {type(x).__name__}")

    @functools.cached_property
    def _jax_phi(self):
        return _jax_fn(self)

    # -- exact hits ------------------------------------------------------------------------
    @functools.cached_property
    def _blocks(self):
        """Faces in Morton order, grouped in blocks of ``_BLOCK`` with bounding balls, plus the
        per-face edge ids and orientation signs used by the watertight edge test."""
        V, F = self.vertices, self.faces
        order = _morton_order(V[F].mean(axis=1))
        m = F.shape[0]
        nb = -(-m // _BLOCK)
        pad = np.concatenate([order, np.full(nb * _BLOCK - m, order[-1])])  # repeat the last face to fill
        blocks = pad.reshape(nb, _BLOCK)
        pts = V[F[blocks]].reshape(nb, -1, 3)
        lo, hi = pts.min(axis=1), pts.max(axis=1)
        centre = 0.5 * (lo + hi)
        radius = np.max(np.linalg.norm(pts - centre[:, None], axis=2), axis=1) * (1 + 1e-9)
        tri = V[F]  # each face's own ball, the same construction: the second cull
        f_lo, f_hi = tri.min(axis=1), tri.max(axis=1)
        f_centre = 0.5 * (f_lo + f_hi)
        f_radius = np.max(np.linalg.norm(tri - f_centre[:, None], axis=2), axis=1) * (1 + 1e-9)
        # edges: (p, q) with p < q, one id per undirected edge; sign −1 where a face runs q → p
        fe = np.stack([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]], axis=1)  # (m, 3, 2) directed
        lo_e, hi_e = fe.min(axis=2), fe.max(axis=2)
        keys = lo_e * V.shape[0] + hi_e
        uniq, inv = np.unique(keys.ravel(), return_inverse=True)
        edges = np.stack([uniq // V.shape[0], uniq % V.shape[0]], axis=1)
        esign = np.where(fe[:, :, 0] == lo_e, 1.0, -1.0)
        return blocks, centre, radius, edges, inv.reshape(m, 3), esign, f_centre, f_radius

    def ray_hits(self, o: np.ndarray, d: np.ndarray, t_min: float = -np.inf, chunk: int = 2048):
        """All ray–face hits at t > t_min: arrays ``(ray index, t, face)`` (unsorted).  A ray
        through an edge or vertex may appear once per face sharing it (same t to rounding).

        Two culls, each conservative (a ray is kept wherever it passes within a bounding ball,
        padded against rounding): the blocks' balls, then each candidate face's own ball, so
        that the exact edge test runs on the faces a ray passes near (torus mesh, 256² camera:
        26 s → 8.4 s).  Directions need not be unit: the culls measure distance along d/|d|, and
        the edge test and the depth are exact for any d."""
        o, d = _points(o, "o"), _points(d, "d")
        blocks, centre, radius, edges, face_edges, esign, f_centre, f_radius = self._blocks
        V, F, N = self.vertices, self.faces, self.face_normals
        with np.errstate(invalid="ignore", divide="ignore"):
            speed = np.linalg.norm(d, axis=1)
            u = d / speed[:, None]  # the unit direction the culls measure distance along
        out_r, out_t, out_f = [], [], []
        for s in range(0, o.shape[0], chunk):
            oc, dc, uc, vc = o[s : s + chunk], d[s : s + chunk], u[s : s + chunk], speed[s : s + chunk]
            near = _ball_near(centre[None] - oc[:, None], uc[:, None], radius[None], vc[:, None], t_min)
            r_idx, b_idx = np.nonzero(near)
            if r_idx.size == 0:
                continue
            r_idx = np.repeat(r_idx, _BLOCK)
            f_idx = blocks[b_idx].ravel()
            keep = np.ones(r_idx.size, bool)  # padded blocks repeat a face: drop the repeats
            keep[1:] = ~((r_idx[1:] == r_idx[:-1]) & (f_idx[1:] == f_idx[:-1]))
            r_idx, f_idx = r_idx[keep], f_idx[keep]
            keep = _ball_near(f_centre[f_idx] - oc[r_idx], uc[r_idx], f_radius[f_idx], vc[r_idx], t_min)
            r_idx, f_idx = r_idx[keep], f_idx[keep]
            ro, rd = oc[r_idx], dc[r_idx]
            # signed volumes ⟨(p − o) × (q − o), d⟩ on each edge in canonical order
            eid = face_edges[f_idx]  # (k, 3)
            p, q = V[edges[eid, 0]], V[edges[eid, 1]]  # (k, 3, 3)
            e = np.einsum("kjc,kc->kj", np.cross(p - ro[:, None], q - ro[:, None]), rd) * esign[f_idx]
            inside = (np.all(e >= 0, axis=1) | np.all(e <= 0, axis=1)) & np.any(e != 0, axis=1)
            n = N[f_idx]
            nd = np.einsum("kc,kc->k", n, rd)
            with np.errstate(invalid="ignore", divide="ignore"):
                t = np.einsum("kc,kc->k", n, V[F[f_idx, 0]] - ro) / nd
            ok = inside & (nd != 0) & np.isfinite(t) & (t > t_min)
            out_r.append(r_idx[ok] + s)
            out_t.append(t[ok])
            out_f.append(f_idx[ok])
        if not out_r:
            return np.zeros(0, np.int64), np.zeros(0), np.zeros(0, np.int64)
        return np.concatenate(out_r), np.concatenate(out_t), np.concatenate(out_f)

    def first_hit(self, o, d, t_min: float = 0.0):
        """First ray–face hit at t > t_min (inf: miss); a touch of a silhouette edge counts."""
        o, d = _points(o, "o"), _points(d, "d")
        r, t, _ = self.ray_hits(o, d, t_min)
        out = np.full(o.shape[0], np.inf)
        np.minimum.at(out, r, t)
        return out

    def ray_intervals(self, o, d):
        o, d = _points(o, "o"), _points(d, "d")
        r, t, _ = self.ray_hits(o, d, -np.inf)
        order = np.lexsort((t, r))
        r, t = r[order], t[order]
        starts = np.searchsorted(r, np.arange(o.shape[0] + 1))
        out = []
        mids_of, reps_of = [], []
        for i in range(o.shape[0]):
            ts = t[starts[i] : starts[i + 1]]
            if ts.size:
                gap = np.diff(ts) > 1e-12 * (np.abs(ts[1:]) + self.size)
                reps = ts[np.concatenate([[True], gap])]
            else:
                reps = ts
            reps_of.append(reps)
            mids_of.append(0.5 * (reps[:-1] + reps[1:]))
        counts = np.array([m.size for m in mids_of])
        if counts.sum():
            ridx = np.repeat(np.arange(o.shape[0]), counts)
            tm = np.concatenate(mids_of)
            inside_all = self.closest(o[ridx] + tm[:, None] * d[ridx])[0] < 0
        else:
            inside_all = np.zeros(0, bool)
        pos = 0
        for reps, k in zip(reps_of, counts):
            inside = np.concatenate([[False], inside_all[pos : pos + k], [False]])
            pos += k
            out.append(reps[inside[1:] != inside[:-1]] if reps.size else reps)
        return out


# -- torch and jax bridges -------------------------------------------------------------------


def _torch_phi(mesh: MeshSDF, x):
    return _torch_fn()(x, mesh)


@functools.cache
def _torch_fn():
    import torch

    class _MeshPhi(torch.autograd.Function):
        """φ by a host call; ∇φ from the same call drives backward and forward-mode jvp."""

        @staticmethod
        def forward(x, mesh):
            phi, g = mesh._host(x.detach().to("cpu", torch.float64).numpy(), True)
            return (torch.as_tensor(phi).to(device=x.device, dtype=x.dtype),
                    torch.as_tensor(g).to(device=x.device, dtype=x.dtype))

        @staticmethod
        def setup_context(ctx, inputs, output):
            ctx.mark_non_differentiable(output[1])
            ctx.save_for_backward(output[1])
            ctx.grad_phi = output[1]

        @staticmethod
        def backward(ctx, gphi, _gg):
            if torch.is_grad_enabled():  # create_graph=True: a second derivative is coming
                raise RuntimeError(
                    "MeshSDF: the torch φ of a mesh is differentiable once (∇φ = (x − c)/φ comes from the host "
                    "closest point c, a constant to autograd); second derivatives (create_graph=True, Hessians) are "
                    "not provided. Differentiate without create_graph, or use a scene with closed-form curvature")
            (g,) = ctx.saved_tensors
            return gphi[..., None] * g, None

        @staticmethod
        def jvp(ctx, dx, _mesh):
            return (ctx.grad_phi * dx).sum(-1), None

    return lambda x, mesh: _MeshPhi.apply(x, mesh)[0]


def _jax_fn(mesh: MeshSDF):
    """The jax φ of ``mesh``, built once per mesh (so jit caches see one function): the host
    query as a custom call named by the mesh data's SHA-256 (:mod:`reference.jax_host_call`), so
    that programs tracing it are kept by jax's persistent compilation cache."""
    import jax
    import jax.numpy as jnp

    from .jax_host_call import host_call

    key = f"isobench_mesh_{mesh._static_spec()['data_sha256'][:24]}"

    def host_phi(x):
        return (mesh._host(x, False),)

    def host_phi_grad(x):
        return mesh._host(x, True)

    @jax.custom_jvp
    def phi(x):
        return host_call(key + "_phi", host_phi, x, (jax.ShapeDtypeStruct(x.shape[:-1], x.dtype),))[0]

    @phi.defjvp
    def phi_jvp(primals, tangents):
        (x,), (dx,) = primals, tangents
        p, g = host_call(key + "_phi_grad", host_phi_grad, x, (jax.ShapeDtypeStruct(x.shape[:-1], x.dtype),
                                                              jax.ShapeDtypeStruct(x.shape, x.dtype)))
        return p, jnp.sum(g * dx, axis=-1)

    return phi
