"""Point-wise quantities at given hits x = o + t_hit d: unit normal and curvatures.

Written once against ``xp``; a backend supplies ``backend.grad_hess(scene, x, hess, theta=None)
-> (g, H, cost)`` — ∇φ (n, 3), the Hessian H (n, 3, 3) or ``None``, and the φ evaluations per
point it cost (autodiff: 1; numpy central differences: more).

Formulas (R. Goldman, "Curvature formulas for implicit curves and surfaces", CAGD 22, 2005;
lecture 'Properties - Normal' and 'Mean Curvature'):

* normal  n = ∇φ/|∇φ| (outward: φ grows outwards);
* ``curvature_laplacian``  Δφ = tr H — the lecture's "mean curvature"; equals κ1 + κ2 only when
  |∇φ| ≡ 1 near the surface (an SDF);
* ``curvature_divergence``  ∇·(∇φ/|∇φ|) = (tr H − nᵀHn)/|∇φ| = κ1 + κ2 for *any* φ (the sum of
  principal curvatures, positive for a sphere: 2/r);
* ``gaussian_curvature``  K = κ1κ2 = ∇φᵀ adj(H) ∇φ / |∇φ|⁴, adj the adjugate (cofactor matrix of
  the symmetric H).

Status per ray, with the values of the README's table (:func:`finish`): CONVERGED where the
outputs are finite; MISS where t_hit is +inf (no hit to evaluate at: ``t = inf``, outputs NaN);
NON_FINITE where t_hit is NaN or −inf (a depth that is no number: what a root finder reports
for NON_FINITE, BAD_INPUT or LIPSCHITZ_VIOLATED) or ∇φ is not finite or zero (``t`` and every
output NaN); BAD_INPUT for a non-finite ray or a zero direction (every float output NaN, ``t``
included).
"""

from __future__ import annotations

import math

from .rootfind import BAD, CONV, MISS, NONF, bad_rays, final_t


def hit_points(xp, o, d, t_hit):
    """x = o + t d where t_hit is finite (0 elsewhere, so nothing non-finite is evaluated) and the
    initial status of every ray: CONVERGED, MISS where t_hit = +inf, NON_FINITE where it is NaN
    or −inf, BAD_INPUT for a non-finite ray."""
    ok_t = xp.isfinite(t_hit)
    t = xp.where(ok_t, t_hit, xp.zeros_like(t_hit))
    status = xp.where(ok_t, CONV, xp.where(t_hit == math.inf, MISS, NONF))
    status = xp.astype(xp.where(bad_rays(xp, o, d), BAD, status), xp.int32)
    o = xp.where(xp.isfinite(o), o, xp.zeros_like(o))
    d = xp.where(xp.isfinite(d), d, xp.zeros_like(d))
    return o + t[:, None] * d, status


def finish(xp, status, values: dict, t_hit, cost):
    """Mark non-finite outputs NON_FINITE, blank outputs of rays that are not CONVERGED (NaN);
    ``t`` as a root finder reports it (:func:`impls.core.rootfind.final_t`): ``inf`` on MISS, NaN
    on NON_FINITE and BAD_INPUT (like every other output), ``t_hit`` otherwise (ILL_CONDITIONED
    and MAX_ITER keep their value, :mod:`impls.core.param_grad`)."""
    finite = None
    for v in values.values():
        f = xp.isfinite(v) if v.ndim == 1 else xp.all(xp.isfinite(v), axis=tuple(range(1, v.ndim)))
        finite = f if finite is None else finite & f
    status = xp.astype(xp.where((status == CONV) & ~finite, NONF, status), xp.int32)
    ok = status == CONV
    out = {}
    for k, v in values.items():
        mask = ok if v.ndim == 1 else xp.reshape(ok, (-1,) + (1,) * (v.ndim - 1))
        out[k] = xp.where(mask, v, xp.full_like(v, float("nan")))
    out.update(t=final_t(xp, t_hit, status), status=status, iterations=xp.zeros_like(status), evals=xp.full_like(status, cost))
    return out


def normal_from_grad(xp, g):
    gn = xp.sqrt(xp.sum(g * g, axis=-1))
    return g / gn[:, None], gn


def curvatures(xp, g, H):
    """(Δφ, ∇·n, K) from ∇φ and the Hessian; see the module docstring."""
    n, gn = normal_from_grad(xp, g)
    tr = H[:, 0, 0] + H[:, 1, 1] + H[:, 2, 2]
    nHn = xp.sum(n * xp.sum(H * n[:, None, :], axis=-1), axis=-1)
    a, b, c = H[:, 0, 0], H[:, 1, 1], H[:, 2, 2]
    d, e, f = H[:, 0, 1], H[:, 0, 2], H[:, 1, 2]
    # cofactors of the symmetric H
    c00, c11, c22 = b * c - f * f, a * c - e * e, a * b - d * d
    c01, c02, c12 = e * f - d * c, d * f - b * e, d * e - a * f
    x, y, z = g[:, 0], g[:, 1], g[:, 2]
    gag = c00 * x * x + c11 * y * y + c22 * z * z + 2 * (c01 * x * y + c02 * x * z + c12 * y * z)
    return tr, (tr - nHn) / gn, gag / gn**4


def normal(backend, scene, o, d, *, t_min, t_max, t_hit, **knobs):
    xp = backend.xp
    x, status = hit_points(xp, o, d, t_hit)
    g, _, cost = backend.grad_hess(scene, x, False)
    nrm, _ = normal_from_grad(xp, g)
    return finish(xp, status, {"normal": nrm}, t_hit, cost)


def curvature(backend, scene, o, d, *, t_min, t_max, t_hit, **knobs):
    xp = backend.xp
    x, status = hit_points(xp, o, d, t_hit)
    g, H, cost = backend.grad_hess(scene, x, True)
    lap, div, gauss = curvatures(xp, g, H)
    nrm, _ = normal_from_grad(xp, g)
    return finish(xp, status, {"curvature_laplacian": lap, "curvature_divergence": div,
                               "gaussian_curvature": gauss, "normal": nrm}, t_hit, cost)


IMPLS = {"normal": normal, "curvature": curvature}
