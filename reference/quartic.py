"""Ray–torus intersection: the quartic, solved robustly and polished (float64 numpy).

Torus about the z axis, major radius R, minor radius r: φ(x) = √((ρ − R)² + z²) − r with
ρ = √(x² + y²).  Its surface is the zero set of the quartic
(|x|² + R² − r²)² − 4R²(x² + y²).

Method (why each step):

1. Shift the ray parameter to the point of closest approach to the centre, t = t_c + s with
   t_c = −o·e (e = d/|d|), so that |x(s)|² = |o_c|² + s² and the quartic in s is already
   depressed: s⁴ + c₂ s² + c₁ s + c₀.  Far origins (1e6) therefore do not enter the
   coefficients; a ray whose line passes farther than R + r from the centre misses.
2. Candidate roots: eigenvalues of the companion matrix (numpy's ``eigvals``; a library solver
   rather than Ferrari's formulas, which lose accuracy near multiple roots).  Only their real
   parts are used, as *separators*: probes at −B, the midpoints of consecutive real parts, and
   +B (B beyond the bounding sphere, where φ > 0).  A conjugate pair produced by a perturbed
   double root puts a probe exactly at the cluster centre, which separates its two roots.
3. Polish: every sign change of the float64 SDF between consecutive probes is bisected to
   adjacent floats of the *SDF along the ray* (not the quartic, whose coefficients suffer
   cancellation).  The error is then that of evaluating φ (a few ulp of R + r) divided by
   |∂φ/∂t| — the problem's own condition number.
4. Tangent (double) roots: a probe where |φ| ≤ 8·eps·(R + r + |o_c|) with no crossing nearby is
   a touching point; it is a hit (φ = 0 there) but bounds no interval.  Its position is
   determined only to O(√eps) by any float64 method, since φ ≈ (Δs)²/(2r) near it.
"""

from __future__ import annotations

import numpy as np

EPS = np.finfo(np.float64).eps


def _torus_sdf_np(x: np.ndarray, R: float, r: float) -> np.ndarray:
    rho = np.hypot(x[..., 0], x[..., 1])
    return np.hypot(rho - R, x[..., 2]) - r


def ray_torus(o: np.ndarray, d: np.ndarray, R: float, r: float):
    """Crossings and tangent touches of rays o + t d with the torus (R, r) about z.

    Returns ``(crossings, tangents)``: lists (one per ray) of sorted float64 arrays of t.
    Crossings alternate enter/exit (φ changes sign); tangents are touching points."""
    o = np.asarray(o, np.float64)
    d = np.asarray(d, np.float64)
    n = o.shape[0]
    dn = np.linalg.norm(d, axis=1)
    e = d / dn[:, None]
    tc = -np.einsum("ij,ij->i", o, e)
    oc = o + tc[:, None] * e
    B = 1.25 * (R + r)
    near = np.linalg.norm(oc, axis=1) < (R + r) * (1 + 1e-12)
    crossings = [np.zeros(0) for _ in range(n)]
    tangents = [np.zeros(0) for _ in range(n)]
    idx = np.flatnonzero(near)
    if idx.size == 0:
        return crossings, tangents
    oc_, e_, tc_, dn_ = oc[idx], e[idx], tc[idx], dn[idx]
    A = np.einsum("ij,ij->i", oc_, oc_) + R * R - r * r
    exy2 = e_[:, 0] ** 2 + e_[:, 1] ** 2
    c2 = 2 * A - 4 * R * R * exy2
    c1 = -8 * R * R * (oc_[:, 0] * e_[:, 0] + oc_[:, 1] * e_[:, 1])
    c0 = A * A - 4 * R * R * (oc_[:, 0] ** 2 + oc_[:, 1] ** 2)
    m = idx.size
    comp = np.zeros((m, 4, 4))
    comp[:, 1, 0] = comp[:, 2, 1] = comp[:, 3, 2] = 1.0
    comp[:, 0, 3] = -c0
    comp[:, 1, 3] = -c1
    comp[:, 2, 3] = -c2
    cand = np.sort(np.clip(np.linalg.eigvals(comp).real, -B, B), axis=1)
    probes = np.concatenate([np.full((m, 1), -B), (cand[:, 1:] + cand[:, :-1]) / 2, np.full((m, 1), B)], axis=1)

    def f(k, s):  # SDF at o_c + s e for rays k
        return _torus_sdf_np(oc_[k] + s[:, None] * e_[k], R, r)

    rows = np.repeat(np.arange(m), 5)
    fp = f(rows, probes.ravel()).reshape(m, 5)
    inside = fp < 0
    change = inside[:, 1:] != inside[:, :-1]
    kr, kc = np.nonzero(change)
    lo, hi = probes[kr, kc], probes[kr, kc + 1]
    lo_in = inside[kr, kc]
    for _ in range(200):  # bisection to adjacent floats of the float64 SDF's sign change
        mid = lo + (hi - lo) / 2
        active = (mid != lo) & (mid != hi)
        if not active.any():
            break
        mid_in = f(kr, mid) < 0
        go_hi = mid_in == lo_in  # root is in [mid, hi]
        lo = np.where(active & go_hi, mid, lo)
        hi = np.where(active & ~go_hi, mid, hi)
    roots = lo + (hi - lo) / 2
    tol = 8 * EPS * (R + r + np.linalg.norm(oc_, axis=1))
    scale = R + r
    starts = np.searchsorted(kr, np.arange(m + 1))  # np.nonzero lists kr in row order
    for j in range(m):
        s_cross = np.sort(roots[starts[j]:starts[j + 1]])
        tang = []
        for k in (1, 2, 3):
            p = probes[j, k]
            if abs(fp[j, k]) <= tol[j] and not np.any(np.abs(s_cross - p) <= 1e-6 * scale):
                if not any(abs(p - q) <= 1e-12 * scale for q in tang):
                    tang.append(p)
        ray = idx[j]
        crossings[ray] = (tc_[j] + s_cross) / dn_[j]
        tangents[ray] = (tc_[j] + np.asarray(tang, np.float64)) / dn_[j]
    return crossings, tangents
