"""Generate the stored meshes ``reference/data/meshes/*.npz`` (deterministic, no downloads).

    python -m reference.make_meshes        # rewrites the files; the committed files are the truth

Each file holds ``vertices`` (n, 3) float64 and ``faces`` (m, 3) int32 of a closed, watertight,
outward-oriented triangle mesh (checked by :class:`reference.mesh.MeshSDF` on load).  All three
are generated here from formulas, so they are this project's own work under its licence; no
scanned model ships inside the installed packages (scikit-image's data holds images only,
trimesh's and libigl's test models are not installed), so the "scan-like" shape is synthetic.

* ``torus``: genus 1.  ``trimesh.creation.torus(R = 1, r = 0.25, 64 major × 32 minor sections)``:
  4096 faces whose vertices lie on the analytic torus |(√(x² + y²) − R, z)| = r
  (:class:`reference.primitives.Torus`), so the mesh differs from it by at most the sagitta
  R(1 − cos(π/64)) + r(1 − cos(π/32)) ≈ 1.8e-3 inward.
* ``fin``: sharp edges and a thin part.  A block [−0.5, 0.5]² × [−0.5, −0.1] with a wall
  [−0.004, 0.004] × [−0.4, 0.4] × [−0.1, 0.5] standing on it: the wall is 0.008 thick, 0.46 %
  of the shape's diagonal √3.  Built as the boundary of a union of cells of a non-uniform grid
  (each boundary cell face two triangles), which makes it watertight with no T-junctions.
* ``blob``: organic, scan-like.  An icosphere (4 subdivisions, 5120 faces) with each vertex u
  (|u| = 1) moved to ρ(u) u, ρ(u) = 1 + Σₖ aₖ sin(⟨ωₖ, u⟩ + φₖ) over 8 random waves (seed
  :data:`BLOB_SEED`: ωₖ Gaussian with |ωₖ| scaled into [1.5, 4.5], aₖ = 0.06/(1 + |ωₖ|/3),
  φₖ uniform).  ρ > 0 keeps it star-shaped, hence closed and embedded; the script checks that no
  face turned over (each face normal has a positive radial component).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

DIR = Path(__file__).with_name("data") / "meshes"
BLOB_SEED = 18


def torus() -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    m = trimesh.creation.torus(1.0, 0.25, major_sections=64, minor_sections=32)
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces)


def grid_solid(xs, ys, zs, occupied: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The outward-oriented boundary of the union of occupied cells of the grid xs × ys × zs
    (``occupied[i, j, k]`` for the cell [xs[i], xs[i+1]] × …): two triangles per cell face
    between an occupied and an empty cell.  Cells meeting only along an edge or at a vertex
    would make it non-manifold; the caller avoids them."""
    xs, ys, zs = (np.asarray(a, np.float64) for a in (xs, ys, zs))
    shape = (len(xs), len(ys), len(zs))
    gx, gy, gz = np.meshgrid(xs, ys, zs, indexing="ij")
    V = np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1)
    node = lambda i, j, k: (i * shape[1] + j) * shape[2] + k
    occ = np.pad(occupied.astype(bool), 1)  # an empty border: index shifts by 1
    faces = []
    for axis in range(3):
        step = np.eye(3, dtype=int)[axis]
        u, v = np.eye(3, dtype=int)[(axis + 1) % 3], np.eye(3, dtype=int)[(axis + 2) % 3]
        for c in np.argwhere(occupied):
            for sgn in (1, -1):
                nb = c + 1 + sgn * step
                if occ[tuple(nb)]:
                    continue
                base = c + (step if sgn > 0 else 0)  # the face's lowest corner
                quad = [base, base + u, base + u + v, base + v]  # counter-clockwise about +axis
                if sgn < 0:
                    quad = quad[::-1]
                q = [node(*p) for p in quad]
                faces += [[q[0], q[1], q[2]], [q[0], q[2], q[3]]]
    F = np.array(faces, np.int64)
    used, F = np.unique(F, return_inverse=True)
    return V[used], F.reshape(-1, 3)


def fin() -> tuple[np.ndarray, np.ndarray]:
    xs, ys, zs = [-0.5, -0.004, 0.004, 0.5], [-0.5, -0.4, 0.4, 0.5], [-0.5, -0.1, 0.5]
    occ = np.zeros((3, 3, 2), bool)
    occ[:, :, 0] = True  # the block
    occ[1, 1, 1] = True  # the wall
    return grid_solid(xs, ys, zs, occ)


def blob(seed: int = BLOB_SEED) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=4)
    u = np.asarray(m.vertices, np.float64)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    rng = np.random.default_rng(seed)
    w = rng.normal(size=(8, 3))
    w *= (rng.uniform(1.5, 4.5, 8) / np.linalg.norm(w, axis=1))[:, None]
    amp = 0.06 / (1 + np.linalg.norm(w, axis=1) / 3)
    phase = rng.uniform(0, 2 * np.pi, 8)
    rho = 1.0 + np.sin(u @ w.T + phase) @ amp
    V = rho[:, None] * u
    F = np.asarray(m.faces)
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    if np.any(np.einsum("ij,ij->i", n, V[F].mean(axis=1)) <= 0):
        raise AssertionError("a blob face turned over; lower the wave amplitudes")
    return V, F


SHAPES = {"torus": torus, "fin": fin, "blob": blob}


def main() -> None:
    from .mesh import MeshSDF

    DIR.mkdir(parents=True, exist_ok=True)
    for name, make in SHAPES.items():
        V, F = make()
        MeshSDF(V, F, name=name)  # validates: watertight, consistently oriented, outward
        path = DIR / f"{name}.npz"
        np.savez_compressed(path, vertices=V, faces=F.astype(np.int32))
        print(f"wrote {path}: {V.shape[0]} vertices, {F.shape[0]} faces, {path.stat().st_size} bytes")


if __name__ == "__main__":
    main()
