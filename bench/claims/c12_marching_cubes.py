"""Claim 12: marching cubes (Lorensen & Cline 1987) extracts the zero level set; the mesh converges to the
surface as the grid refines (lecture, "Discrete Representations of Implicit Function").

φ is sampled on an n³ grid over [−1.5, 1.5]³ (shifted by 0.1234 h so the surface is not aligned with
the grid), ``skimage.measure.marching_cubes`` extracts the level 0.  Distances against the *exact*
surface:
* mesh → surface: |SDF(p)| exactly (the shapes' exact SDF), at every vertex, edge midpoint and
  centroid of every triangle (a dense sample of the mesh, so a lower bound of the one-sided
  Hausdorff distance that is tight to O(h³));
* surface → mesh: exact surface points from the parametrisation, distance to the triangle mesh by
  libigl's ``point_mesh_squared_distance`` (exact point–triangle distance, AABB tree).
Hausdorff = max of the two maxima; Chamfer = mean of the two mean distances.  Rates: least-squares
slope of log distance against log h.
"""

from __future__ import annotations

import numpy as np

from reference import AlgebraicSphere, Sphere

from .adapters import label
from .scenes import surface_points, torus
from .figures import figure
from .ledger import LEDGER, Evidence, Trial
from .stats import fit_power


def _shapes():
    sph, tor = Sphere(), torus()
    return [
        ("sphere", sph, sph.value),
        ("torus", tor, tor.value),
        # the lecture's non-SDF x²+y²+z²−1: same surface, distances from the sphere's exact SDF
        ("sphere", AlgebraicSphere(), sph.value),
    ]


def mesh_distances(shape, sdf, fam, n, rng, n_surface=20_000):
    import igl
    from skimage.measure import marching_cubes

    h = 3.0 / (n - 1)
    g = -1.5 + 0.1234 * h + h * np.arange(n)
    X = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1)
    vol = shape.value(X)
    verts, faces, _, _ = marching_cubes(vol, level=0.0, spacing=(h, h, h))
    verts = verts + g[0]
    tri = verts[faces]
    probes = np.concatenate([verts, tri.mean(1), 0.5 * (tri[:, 0] + tri[:, 1]), 0.5 * (tri[:, 1] + tri[:, 2]),
                             0.5 * (tri[:, 2] + tri[:, 0])])
    d_ms = np.abs(sdf(probes))
    surf = surface_points(fam, n_surface, rng)
    sq, _, _ = igl.point_mesh_squared_distance(surf, verts, faces.astype(np.int64))
    d_sm = np.sqrt(sq)
    return h, max(d_ms.max(), d_sm.max()), 0.5 * (d_ms.mean() + d_sm.mean()), len(faces)


@LEDGER.claim(
    "12",
    statement="marching cubes extracts the iso-surface: the mesh converges to the surface as the grid refines",
    equation="slide 'Discrete Representations of Implicit Function' (Lorensen & Cline 1987)",
    how_checked="skimage marching cubes on n³ grids of [−1.5,1.5]³ (n = 16…64; full: …192) for the sphere SDF, "
    "a torus SDF and x²+y²+z²−1; Hausdorff and Chamfer distance to the exact surface; a trial (shape) holds "
    "if the Hausdorff distance decreases with every refinement and its fitted rate in h is > 0",
    scope="smooth closed surfaces (SDFs and non-SDF implicits) sampled on uniform grids that refine",
)
def check_mc(ctx):
    ns = [16, 24, 32, 48, 64] + ([] if ctx.quick else [96, 128, 192])
    rng = np.random.default_rng(ctx.seed + 12)
    trials, key, curves = [], {}, []
    for fam, shape, sdf in _shapes():
        rows = [mesh_distances(shape, sdf, fam, n, rng) for n in ns]
        h = np.array([r[0] for r in rows])
        haus = np.array([r[1] for r in rows])
        cham = np.array([r[2] for r in rows])
        rate_h, _ = fit_power(h, haus)
        rate_c, _ = fit_power(h, cham)
        mono = bool(np.all(np.diff(haus) < 0))
        name = label(shape)
        trials.append(Trial(name, mono and rate_h > 0, {"hausdorff_rate": rate_h, "chamfer_rate": rate_c,
                                                              "hausdorff_finest": float(haus[-1])}))
        key[f"{name}: Hausdorff rate in h"] = rate_h
        key[f"{name}: Chamfer rate in h"] = rate_c
        key[f"{name}: Hausdorff at n={ns[0]}, n={ns[-1]}"] = [float(haus[0]), float(haus[-1])]
        key[f"{name}: triangles at n={ns[-1]}"] = int(rows[-1][3])
        curves.append((name, h, haus, cham))
    fig, (ax,) = figure(1, 1, 6.5, 4.5)
    for name, h, haus, cham in curves:
        line = ax.loglog(h, haus, "o-", label=f"Hausdorff, {name}")[0]
        ax.loglog(h, cham, "s--", color=line.get_color(), label=f"Chamfer, {name}")
    ax.loglog(h, 0.5 * h**2, "k:", label="∝ h²")
    ax.set_xlabel("grid spacing h (length units)")
    ax.set_ylabel("distance to the exact surface (length units)")
    ax.legend(fontsize=6)
    return Evidence(trials, key, fig)
