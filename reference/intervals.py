"""Ray interval sets: the exact geometry of CSG along a ray.

Along one ray the inside {t : φ(o + t d) < 0} of a scene is a finite union of open intervals,
stored as a sorted float64 array of boundaries ``[enter₀, exit₀, enter₁, exit₁, …]`` (shape
``(2k,)``, ±inf allowed).  CSG acts on these sets exactly (Roth, "Ray casting for modeling
solids", Computer Graphics and Image Processing 18, 1982): union, intersection, complement
and difference are set operations on the intervals, so a CSG hit is a child's exact hit.

Touching intervals (one ends where the next starts) are merged: the common boundary is a
point where the union's φ = 0 without a sign change, not a surface crossing.
"""

from __future__ import annotations

import numpy as np

EMPTY = np.zeros(0)


def from_bounds(t0: np.ndarray, t1: np.ndarray) -> list[np.ndarray]:
    """One interval (t0, t1) per ray, empty where t0 < t1 fails (NaN bounds mean empty)."""
    return [np.array([a, b]) if a < b else EMPTY for a, b in zip(np.asarray(t0, float), np.asarray(t1, float))]


def union(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    pairs = np.concatenate([a, b]).reshape(-1, 2)
    if pairs.shape[0] == 0:
        return EMPTY
    pairs = pairs[np.argsort(pairs[:, 0], kind="stable")]
    out = [list(pairs[0])]
    for s, e in pairs[1:]:
        if s <= out[-1][1]:
            out[-1][1] = max(out[-1][1], e)
        else:
            out.append([s, e])
    return np.asarray(out, np.float64).ravel()


def intersection(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    pa, pb = a.reshape(-1, 2), b.reshape(-1, 2)
    out = []
    i = j = 0
    while i < len(pa) and j < len(pb):
        s, e = max(pa[i, 0], pb[j, 0]), min(pa[i, 1], pb[j, 1])
        if s < e:
            out.extend((s, e))
        if pa[i, 1] < pb[j, 1]:
            i += 1
        else:
            j += 1
    return np.asarray(out, np.float64)


def complement(a: np.ndarray) -> np.ndarray:
    b = np.concatenate([[-np.inf], a, [np.inf]]).reshape(-1, 2)
    b = b[b[:, 0] < b[:, 1]]
    return b.ravel()


def difference(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return intersection(a, complement(b))


def map_rays(op, *per_ray: list[np.ndarray]) -> list[np.ndarray]:
    """Apply a binary/unary interval operation ray by ray."""
    return [op(*args) for args in zip(*per_ray)]
