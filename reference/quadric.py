"""Numerically stable ray–quadric root formulas (float64 numpy).

Source: M. Pharr, W. Jakob, G. Humphreys, *Physically Based Rendering* 4th ed. (pbrt-v4,
``Sphere::BasicIntersect``) and W. Kahan / Press et al. *Numerical Recipes* §5.6 for the
cancellation-free quadratic.
"""

from __future__ import annotations

import numpy as np


def ray_sphere_roots(o: np.ndarray, d: np.ndarray, center: np.ndarray, radius: float):
    """Both roots t0 ≤ t1 of |o + t d − c|² = r² per ray (NaN where the ray misses).

    With f = o − c, a = d·d and the half-coefficient b = f·d, the discriminant b² − a(|f|² − r²)
    is formed as a (r + ℓ)(r − ℓ), ℓ = |f − (b/a) d| the distance from c to the ray's line
    (pbrt-v4), so grazing rays keep full relative precision.  The constant term |f|² − r² is
    formed as (|f| − r)(|f| + r), exact to a few ulp when the origin is near the surface.  The
    roots are q/a and c/q with q = −(b + sign(b)√disc) (no subtraction of close numbers).
    A tangent ray (disc = 0) returns the double root twice.
    """
    o = np.asarray(o, np.float64)
    d = np.asarray(d, np.float64)
    f = o - np.asarray(center, np.float64)
    a = np.einsum("...i,...i->...", d, d)
    b = np.einsum("...i,...i->...", f, d)
    perp = f - (b / a)[..., None] * d
    ell = np.linalg.norm(perp, axis=-1)
    r = float(radius)
    disc = a * (r + ell) * (r - ell)
    fn = np.linalg.norm(f, axis=-1)
    c = (fn - r) * (fn + r)
    with np.errstate(invalid="ignore", divide="ignore"):
        sq = np.sqrt(np.where(disc >= 0, disc, np.nan))
        q = -(b + np.copysign(sq, b))
        t_a = q / a
        t_b = np.where(q != 0, c / q, t_a)  # q = 0 only when b = 0 and disc = 0: double root at 0
    t0 = np.fmin(t_a, t_b)
    t1 = np.fmax(t_a, t_b)
    miss = ~(disc >= 0)
    t0[miss] = np.nan
    t1[miss] = np.nan
    return t0, t1


def ray_cylinder_roots(f_perp: np.ndarray, d_perp: np.ndarray, radius: float):
    """Roots t0 ≤ t1 of |f⊥ + t d⊥|² = r² for an infinite cylinder, given the components of
    (origin − axis point) and of the direction orthogonal to the axis.

    Same stable formula as :func:`ray_sphere_roots` (it does not assume |d⊥| = 1).  A ray
    parallel to the axis (d⊥ = 0) is inside for all t when |f⊥| < r: roots (−inf, inf); else
    NaN (no crossing)."""
    f_perp = np.asarray(f_perp, np.float64)
    d_perp = np.asarray(d_perp, np.float64)
    a = np.einsum("...i,...i->...", d_perp, d_perp)
    par = a == 0
    with np.errstate(invalid="ignore", divide="ignore"):
        t0, t1 = ray_sphere_roots(f_perp, np.where(par[..., None], 1.0, d_perp), np.zeros(f_perp.shape[-1]), radius)
    inside = np.linalg.norm(f_perp, axis=-1) < radius
    t0 = np.where(par, np.where(inside, -np.inf, np.nan), t0)
    t1 = np.where(par, np.where(inside, np.inf, np.nan), t1)
    return t0, t1


def ray_slab(o_axis: np.ndarray, d_axis: np.ndarray, lo: float, hi: float):
    """Interval (t0, t1) where lo < o + t d < hi along one coordinate (one rounded division
    per bound, so each bound is correctly rounded).  d = 0: (−inf, inf) if lo < o < hi, else
    NaN (empty)."""
    o_axis = np.asarray(o_axis, np.float64)
    d_axis = np.asarray(d_axis, np.float64)
    par = d_axis == 0
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):  # overflow: ±inf, which is right
        ta = (lo - o_axis) / d_axis
        tb = (hi - o_axis) / d_axis
    t0, t1 = np.fmin(ta, tb), np.fmax(ta, tb)
    inside = (lo < o_axis) & (o_axis < hi)
    t0 = np.where(par, np.where(inside, -np.inf, np.nan), t0)
    t1 = np.where(par, np.where(inside, np.inf, np.nan), t1)
    return t0, t1
