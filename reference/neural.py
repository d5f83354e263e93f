"""A trained neural SDF as a scene: an IDR-style softplus MLP fitted to a mesh's signed distance.

φ(x) = σ(… σ(x W₁ + b₁) W₂ + b₂ …) W_K + b_K (row vectors, ``xp.matmul``), weights from
``reference/data/neural_blob.npz`` (3 → 64 → 64 → 1, trained on the ``blob`` mesh by
:mod:`reference.make_neural_sdf`).  θ = (W₁, b₁, …, W_K, b_K) flattened row-major.

Activation: the β-softplus of IDR (Yariv et al. 2020), β = 100, written as

    σ(z) = max(z, 0) + log1p(exp(−β|z|))/β,     max(z, 0) computed as (z + |z|)/2 (exact),

which is log(1 + e^{βz})/β without overflow for any z.  Every library evaluates this same
formula; only its ``exp`` and ``log1p`` are libm/SLEEF/XLA's own, which differ in the last bit
(a relative 1e-16 of a term ≤ log 2/β), so numpy, torch and jax agree to float64 rounding, not
bit for bit.  Its derivatives: σ'(z) = s(βz) (the logistic function s, monotone from 0 to 1, so
sup σ' = 1) and σ''(z) = β s(1 − s) ≤ β/4.  Under autodiff the formula's derivative at z = 0 is
½(1 + sign 0) + 0 = ½ = s(0) in torch and jax alike.

Lipschitz bounds (constructor argument ``lipschitz``):

* ``"spectral"`` — L = ∏ₖ ‖Wₖ‖₂ · (sup σ')^{K−1} = ∏ₖ ‖Wₖ‖₂ (lecture eqs. 4–6; exact spectral
  norms by SVD): certified on all of ℝ³ (``SceneInfo.domain`` None).
* ``"local"`` — a tighter bound certified on the *domain* D, the box stored with the weights (the
  mesh's bounding box padded by 0.3): L = sup_D |∇φ| bounded by interval bound propagation
  (Gowal et al., "On the effectiveness of interval bound propagation for training verifiably
  robust models", 2018) of the pre-activations over cells of D, giving intervals of σ'(zₖ)
  (σ' is monotone), and a backward interval pass of ∇φ = W₁ D₁ W₂ D₂ ⋯ w_K (Dₖ = diag σ'(zₖ)), as
  Fast-Lip bounds the gradient of a ReLU network by its activation pattern's intervals (Weng et
  al., "Towards fast computation of certified robustness for ReLU networks", ICML 2018).  Every
  product is centre–radius (c ± r: c' = W c, r' = |W| r), which keeps the cancellation between
  neurons in the centres.  A cell's bound is the largest |g| over its interval box of gradients,
  √Σᵢ(|cᵢ| + rᵢ)²; L is the largest over cells, refined by branch and bound (cells whose bound
  exceeds the best gradient norm found so far by more than 2% are split in eight) and rounded
  outward (:func:`_affine`).  D is convex, so by the mean-value theorem |φ(x) − φ(y)| ≤ L|x − y|
  for x, y ∈ D; the root finders rely on it only inside the scene's ray bounds, which lie in D.
* ``"measured"`` — 1.05 × the largest |∇φ| found on D by sampling (2·10⁵ points) and local
  maximisation from the best of them (L-BFGS-B on |∇φ|², with the closed-form Hessian), in the
  spirit of CLEVER (Weng et al., "Evaluating the robustness of neural networks: an extreme
  value theory approach", ICLR 2018).  **Not certified**: a sample can miss the maximum.  It is
  offered to show what an optimistic L buys and what it risks: every step of a root finder and
  every sample of the numerical reference checks it, and a slope above it is flagged
  (LIPSCHITZ_VIOLATED, a NaN reference hit), never trusted silently.

Ray bounds (all three modes): a box B ⊂ D certified to contain every point where φ ≤ 0
(:func:`certify_surface_box`): φ > 0 is shown by interval bounds on every cell of D outside B,
and outside D by the same intervals in the coordinates x = c + (h ⊙ v)/ρ (v on the unit cube's
surface, ρ ∈ (0, 1]), in which ρ·φ is a network with the softplus sharpened to β/ρ and biases
scaled by ρ — finite as ρ → 0, so one finite set of cells covers the unbounded outside.

Exact answers: hits from the certified numerical reference (:mod:`reference.numerical`); ∇φ, the
Hessian (forward-mode in closed form) and ∂φ/∂θ (back-propagation) in closed form, hence normals,
principal curvatures and dt/dθ at the hits.
"""

from __future__ import annotations

import functools
import hashlib
import math
import time
from pathlib import Path

import numpy as np

from .curvature import principal_from_hessian
from .raybounds import box_chord
from .scene import Field, SceneInfo, _points

DEFAULT = Path(__file__).with_name("data") / "neural_blob.npz"
MODES = ("spectral", "local", "measured")
MEASURED_FACTOR = 1.05
EPS = float(np.finfo(np.float64).eps)


# -- the activation -------------------------------------------------------------------------

def softplus(xp, z, beta: float):
    """σ(z) = max(z, 0) + log1p(exp(−β|z|))/β with max(z, 0) = (z + |z|)/2 (any array library)."""
    a = xp.abs(z)
    return 0.5 * (z + a) + xp.log1p(xp.exp(-beta * a)) / beta


def logistic(u):
    """s(u) = 1/(1 + e^{−u}) without overflow (numpy): σ'(z) = s(βz)."""
    e = np.exp(-np.abs(u))
    return np.where(u >= 0, 1.0 / (1.0 + e), e / (1.0 + e))


# -- interval arithmetic (numpy, float64, rounded outward) -------------------------------------

def _affine(c, r, W, b):
    """Centre–radius image of the box c ± r under y = x W + b: (c W + b, r |W| + rounding).

    The rounding term bounds the float64 error of both products (Higham, *Accuracy and Stability
    of Numerical Algorithms*, 2nd ed., §3.1: |fl(xᵀw) − xᵀw| ≤ γₙ |x|ᵀ|w|, γₙ = nu/(1 − nu)) by
    (n + 3)ε · max_i(|cᵢ| + rᵢ) · Σᵢ|Wᵢⱼ| + (n + 3)ε|bⱼ| per output j — looser than γₙ|x|ᵀ|w|
    but a row maximum instead of a third matrix product."""
    k = W.shape[0]
    lead = np.shape(c)[:-1]
    c2, r2 = np.reshape(c, (-1, k)), np.reshape(r, (-1, k))  # 2-D products: numpy's batched matmul is slower
    aW = np.abs(W)
    cc = c2 @ W
    rr = r2 @ aW
    mag = np.max(np.abs(c2) + r2, axis=-1, keepdims=True)
    gam = (k + 3) * EPS
    rr += gam * (mag * aW.sum(axis=0) + np.abs(b) + np.abs(cc) + rr)
    cc += b
    cc, rr = cc.reshape(lead + (W.shape[1],)), rr.reshape(lead + (W.shape[1],))
    return cc, rr


def _from_bounds(lo, hi):
    """Centre–radius form of [lo, hi], rounded outward (c ± r ⊇ [lo, hi])."""
    c = lo + 0.5 * (hi - lo)
    r = np.maximum(hi - c, c - lo)
    return c, r * (1 + 4 * EPS) + EPS * np.abs(c)


def _down(v, z=0.0):
    """v lowered by its evaluation error (exp, log1p, logistic: a few ulp, relative to v and z)."""
    return v - 8 * EPS * (np.abs(v) + np.abs(z))


def _up(v, z=0.0):
    return v + 8 * EPS * (np.abs(v) + np.abs(z))


def _softplus_k(y, k):
    """softplus with sharpness k ∈ (0, ∞] (k = ∞: max(y, 0)), numpy."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        tail = np.where(np.isinf(k), 0.0, np.log1p(np.exp(-k * np.abs(y))) / k)
    return np.maximum(y, 0.0) + tail


def _times_slope(dlo, dhi, c, r):
    """Centre–radius of the product of σ' ∈ [dlo, dhi] (≥ 0) with the interval c ± r."""
    lo, hi = c - r, c + r
    return _from_bounds(_down(np.minimum(dlo * lo, dhi * lo)), _up(np.maximum(dlo * hi, dhi * hi)))


def cell_bounds(layers, beta, c, r):
    """Per cell c ± r (rows of (n, 3)): ``(φ_lo, φ_hi, G)`` with φ_lo ≤ φ ≤ φ_hi and |∇φ| ≤ G on the cell.

    Forward, per layer, each pre-activation's interval is the intersection of two enclosures:
    interval bound propagation (the box through x W + b, σ, …) and the mean-value form
    z(x) ∈ z(x_c) ± Σᵢ |∂z/∂xᵢ|_max hᵢ, with the interval Jacobian ∂z/∂x carried forward
    (J_{k+1} = (σ'(zₖ) ⊙ Jₖ) W_{k+1}, J₁ = W₁).  The mean-value form keeps what interval
    propagation loses — that the 64 hidden values of a cell are functions of 3 coordinates —
    and is the tighter one on small cells.  σ'(z) ∈ [s(β z_lo), s(β z_hi)] (σ' is increasing).
    The gradient box is the intersection of the forward one (the last Jacobian) and the backward
    pass g = W₁(D₁ ⊙ W₂(D₂ ⊙ ⋯ w_K)); G = √Σᵢ max(|gᵢ,lo|, |gᵢ,hi|)².  φ's interval is
    intersected with φ(x_c) ± G|h|.  Every step is rounded outward."""
    n = c.shape[0]
    ac, ar = c, r  # the activation's enclosure over the cell
    pc, pr = c, np.zeros_like(c)  # the value at the cell's centre (radius: its rounding)
    Jc = np.broadcast_to(np.eye(3), (n, 3, 3))  # ∂a/∂x as (n, 3, width), a = x for the input
    Jr = np.zeros((n, 3, 3))
    slopes = []
    for k, (W, b) in enumerate(layers):
        zc, zr = _affine(ac, ar, W, b)
        qc, qr = _affine(pc, pr, W, b)
        Jc, Jr = _affine(Jc, Jr, W, np.zeros_like(b))
        mv = qr + np.einsum("nik,ni->nk", np.abs(Jc) + Jr, r)
        lo, hi = np.maximum(zc - zr, _down(qc - mv)), np.minimum(zc + zr, _up(qc + mv))
        if k == len(layers) - 1:
            break
        dlo, dhi = np.maximum(_down(logistic(beta * lo)), 0.0), np.minimum(_up(logistic(beta * hi)), 1.0)
        slopes.append((dlo, dhi))
        ac, ar = _from_bounds(_down(_softplus_k(lo, beta), lo), _up(_softplus_k(hi, beta), hi))
        qlo, qhi = qc - qr, qc + qr
        pc, pr = _from_bounds(_down(_softplus_k(qlo, beta), qlo), _up(_softplus_k(qhi, beta), qhi))
        Jc, Jr = _times_slope(dlo[:, None, :], dhi[:, None, :], Jc, Jr)
    flo, fhi = (Jc - Jr)[..., 0], (Jc + Jr)[..., 0]  # forward-mode gradient box (n, 3)
    gc = np.broadcast_to(layers[-1][0][:, 0], (n, layers[-1][0].shape[0]))
    gr = np.zeros_like(gc)
    for (W, _), (dlo, dhi) in zip(reversed(layers[:-1]), reversed(slopes)):
        uc, ur = _times_slope(dlo, dhi, gc, gr)
        gc, gr = _affine(uc, ur, W.T, np.zeros(W.shape[0]))
    glo, ghi = np.maximum(flo, gc - gr), np.minimum(fhi, gc + gr)
    G = np.sqrt(np.sum(np.maximum(np.abs(glo), np.abs(ghi)) ** 2, axis=-1)) * (1 + 8 * EPS)
    reach = G * np.sqrt(np.sum(r * r, axis=-1)) * (1 + 8 * EPS)
    phi_lo = np.maximum(lo[:, 0], _down(qc[:, 0] - qr[:, 0] - reach))
    phi_hi = np.minimum(hi[:, 0], _up(qc[:, 0] + qr[:, 0] + reach))
    return phi_lo, phi_hi, G


def _far_lower_bound(layers, beta, centre, half, vc, vr, rho_lo, rho_hi):
    """Lower bound of ρ·φ(centre + (half ⊙ v)/ρ) over boxes v ∈ vc ± vr, ρ ∈ [ρ_lo, ρ_hi] ⊂ [0, 1].

    With x = centre + (half ⊙ v)/ρ the first pre-activation is z₁ = y₁/ρ, y₁ = v (half ⊙ W₁) +
    ρ(centre W₁ + b₁); then ρσ(y/ρ) = softplus_{β/ρ}(y), which increases with y and with ρ
    (a softplus of sharpness k decreases with k towards max(y, 0)), and ρz_{k+1} = (ρaₖ)W_{k+1} +
    ρb_{k+1}: every layer is an interval map of (v, ρ) with ρb an interval too."""
    rc, rr = 0.5 * (rho_lo + rho_hi)[:, None], 0.5 * (rho_hi - rho_lo)[:, None]
    k_lo = np.where(rho_hi > 0, beta / np.where(rho_hi > 0, rho_hi, 1.0), np.inf)  # sharpness at ρ_hi (smallest)
    k_hi = np.where(rho_lo > 0, beta / np.where(rho_lo > 0, rho_lo, 1.0), np.inf)
    W1, b1 = layers[0]
    W1s = half[:, None] * W1
    b1s = centre @ W1 + b1
    c, r = vc, vr
    for i, (W, b) in enumerate(layers):
        if i == 0:
            yc, yr = _affine(c, r, W1s, np.zeros_like(b1s))
            bb = b1s
        else:
            yc, yr = _affine(c, r, W, np.zeros_like(b))
            bb = b
        yc = yc + rc * bb  # + ρ b over ρ ∈ rc ± rr
        yr = _up(yr + rr * np.abs(bb), yc)
        if i == len(layers) - 1:
            return (yc - yr)[..., 0]
        ylo, yhi = yc - yr, yc + yr
        c, r = _from_bounds(_down(_softplus_k(ylo, k_hi[:, None]), ylo), _up(_softplus_k(yhi, k_lo[:, None]), yhi))
    raise AssertionError("unreachable")


def _grid_cells(lo, hi, n):
    """The n³ cells of the box [lo, hi]: centres and half-widths (rows)."""
    h = (hi - lo) / (2 * n)
    axes = [lo[i] + h[i] * (2 * np.arange(n) + 1) for i in range(3)]
    c = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    return c, np.broadcast_to(h, c.shape).copy()


def _split8(c, r):
    """Each cell c ± r into its 8 octants."""
    signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing="ij")).reshape(3, 8).T  # (8, 3)
    h = r / 2
    return (c[:, None, :] + signs[None] * h[:, None, :]).reshape(-1, 3), np.repeat(h, 8, axis=0)


def certify_local_lipschitz(net: "NeuralSDF", lo, hi, lower: float, *, cells: int = 12, tol: float = 0.02,
                            rounds: int = 12, split: int = 256) -> dict:
    """A certified upper bound of sup |∇φ| on the box [lo, hi] (module doc, "local").

    Branch and bound on :func:`cell_bounds`: start from ``cells``³ cells; each round splits in
    eight the ``split`` cells of largest bound, until the largest is within (1 + ``tol``) of the
    best |∇φ| seen (``lower``, and |∇φ| at every cell's centre: a lower bound of the supremum)
    or after ``rounds`` rounds.  Returns ``L`` (the largest cell bound: every point of the box
    lies in a cell), ``lower`` (the best |∇φ| seen), ``cells`` (leaves), ``rounds``, ``seconds``."""
    t0 = time.perf_counter()
    layers, beta = net.layers, net.beta
    c, r = _grid_cells(lo, hi, cells)
    ub = cell_bounds(layers, beta, c, r)[2]
    best = max(lower, float(np.max(net.gradient_norm(c))))
    done = 0
    for done in range(1, rounds + 1):
        if np.max(ub) <= (1 + tol) * best:
            done -= 1
            break
        pick = np.argsort(ub)[-split:]
        keep = np.ones(c.shape[0], bool)
        keep[pick] = False
        nc, nr = _split8(c[pick], r[pick])
        nub = cell_bounds(layers, beta, nc, nr)[2]
        best = max(best, float(np.max(net.gradient_norm(nc))))
        c, r, ub = np.concatenate([c[keep], nc]), np.concatenate([r[keep], nr]), np.concatenate([ub[keep], nub])
    return {"L": float(np.max(ub)), "lower": best, "cells": int(c.shape[0]), "rounds": done,
            "seconds": time.perf_counter() - t0}


def _far_cells(far_cells: int, far_slabs: int):
    """The initial cells of (v, ρ): each face of the unit cube in ``far_cells``² squares times
    ``far_slabs`` slabs of ρ ∈ [0, 1]: centres and radii of v (the face's fixed coordinate has
    radius 0), and ρ's ends."""
    u = (2 * np.arange(far_cells) + 1) / far_cells - 1
    uu, ww = (a.ravel() for a in np.meshgrid(u, u, indexing="ij"))
    vc, vr = [], []
    for axis in range(3):
        for sgn in (-1.0, 1.0):
            v = np.zeros((uu.size, 3))
            v[:, axis] = sgn
            others = [i for i in range(3) if i != axis]
            v[:, others[0]], v[:, others[1]] = uu, ww
            rad = np.zeros((uu.size, 3))
            rad[:, others] = 1.0 / far_cells
            vc.append(v)
            vr.append(rad)
    vc, vr = np.concatenate(vc), np.concatenate(vr)
    edges = np.linspace(0.0, 1.0, far_slabs + 1)
    m = vc.shape[0]
    return np.repeat(vc, far_slabs, axis=0), np.repeat(vr, far_slabs, axis=0), np.tile(edges[:-1], m), np.tile(edges[1:], m)


def _split_far(vc, vr, rlo, rhi):
    """Each (v, ρ) cell into 8: its two free coordinates of v halved, and ρ halved."""
    free = vr > 0
    axes = np.argwhere(free).reshape(-1, 2, 2)[:, :, 1]  # the two free axes of each row
    rows = np.arange(vr.shape[0])
    rm = 0.5 * (rlo + rhi)
    out = ([], [], [], [])
    for s0 in (-0.5, 0.5):
        for s1 in (-0.5, 0.5):
            off = np.zeros_like(vr)
            off[rows, axes[:, 0]] = s0 * vr[rows, axes[:, 0]]
            off[rows, axes[:, 1]] = s1 * vr[rows, axes[:, 1]]
            for a, b in ((rlo, rm), (rm, rhi)):
                out[0].append(vc + off)
                out[1].append(np.where(free, vr / 2, 0.0))
                out[2].append(a)
                out[3].append(b)
    return tuple(np.concatenate(x) for x in out)


def certify_surface_box(net: "NeuralSDF", *, cells: int = 16, rounds: int = 4, far_cells: int = 4,
                        far_slabs: int = 4, far_rounds: int = 10) -> dict:
    """A box B inside the domain D containing every point of ℝ³ where φ ≤ 0 (module doc).

    Inside D: of ``cells``³ cells, those whose lower bound of φ (:func:`cell_bounds`) is positive
    are dropped; B is the bounding box of the rest.  ``rounds`` times, the remaining cells that
    touch a face of B are split in eight and the positive ones dropped again, which shrinks B
    towards the surface.  B must lie strictly inside D.  Outside D: the cells of (v, ρ) whose lower
    bound of ρφ (:func:`_far_lower_bound`) is positive; the others are split (:func:`_split_far`)
    for up to ``far_rounds`` rounds.  Raises ValueError when either part cannot be certified.
    Returns ``lo``, ``hi`` (B), the cells evaluated and the seconds taken."""
    t0 = time.perf_counter()
    layers, beta = net.layers, net.beta
    lo_d, hi_d = net.domain_lo, net.domain_hi
    c, r = _grid_cells(lo_d, hi_d, cells)
    maybe = cell_bounds(layers, beta, c, r)[0] <= 0
    n_in = c.shape[0]
    c, r = c[maybe], r[maybe]
    if c.shape[0] == 0:
        raise ValueError("the network is positive on its whole domain: no surface to bound")
    for _ in range(rounds):
        blo, bhi = (c - r).min(axis=0), (c + r).max(axis=0)
        edge = np.any((c - r <= blo) | (c + r >= bhi), axis=1)
        nc, nr = _split8(c[edge], r[edge])
        n_in += nc.shape[0]
        m = cell_bounds(layers, beta, nc, nr)[0] <= 0
        c, r = np.concatenate([c[~edge], nc[m]]), np.concatenate([r[~edge], nr[m]])
    blo, bhi = (c - r).min(axis=0), (c + r).max(axis=0)
    margin = 1e-3 * float(np.linalg.norm(hi_d - lo_d))
    if np.any(blo < lo_d + margin) or np.any(bhi > hi_d - margin):
        raise ValueError(f"the set where φ may be ≤ 0 reaches the boundary of the domain "
                         f"[{lo_d.tolist()}, {hi_d.tolist()}]: no ray bounds inside it")
    # outside D: x = centre + (half ⊙ v)/ρ, v on the faces of the unit cube, ρ ∈ (0, 1]
    centre, half = 0.5 * (lo_d + hi_d), 0.5 * (hi_d - lo_d)
    vc, vr, rlo, rhi = _far_cells(far_cells, far_slabs)
    n_far = 0
    for _ in range(far_rounds + 1):
        n_far += vc.shape[0]
        bad = _far_lower_bound(layers, beta, centre, half, vc, vr, rlo, rhi) <= 0
        if not bad.any():
            break
        vc, vr, rlo, rhi = _split_far(vc[bad], vr[bad], rlo[bad], rhi[bad])
    else:
        raise ValueError(f"could not show φ > 0 outside the domain box after {far_rounds} refinements "
                         f"({int(bad.sum())} cells left): the network may have a surface far away")
    return {"lo": blo, "hi": bhi, "cells_inside": int(n_in), "cells_outside": int(n_far),
            "seconds": time.perf_counter() - t0}


def measure_slope(net: "NeuralSDF", lo, hi, *, samples: int = 20_000, starts: int = 6, seed: int = 20260419) -> float:
    """The largest |∇φ| found on the box [lo, hi]: the best of ``samples`` uniform points, then
    L-BFGS-B ascent of |∇φ|² (gradient 2H∇φ, closed-form Hessian) from the ``starts`` best.  A
    lower bound of the supremum (module doc, "measured")."""
    from scipy.optimize import minimize

    x = np.random.default_rng(seed).uniform(lo, hi, size=(samples, 3))
    g = net.gradient_norm(x)
    best = float(g.max())

    def neg(p):
        _, grad, hess = net.gradient_hessian(p[None])
        return -float(grad[0] @ grad[0]), -2.0 * (hess[0] @ grad[0])

    for s in x[np.argsort(g)[-starts:]]:
        res = minimize(neg, s, jac=True, method="L-BFGS-B", bounds=list(zip(lo, hi)), options={"maxiter": 100})
        best = max(best, math.sqrt(max(-float(res.fun), 0.0)))
    return best


#: keys of a stored certificate (``cert_<key>`` in the weights file), computed by :func:`certify`
CERT_KEYS = ("surface_lo", "surface_hi", "local_lo", "local_hi", "measured", "local_L", "local_lower",
             "local_cells", "local_rounds", "surface_cells_inside", "surface_cells_outside")


def certify(net: "NeuralSDF") -> dict:
    """Everything the modes need, from the weights alone: the surface box B
    (:func:`certify_surface_box`), the box of the local bound B' = B grown by 10⁻³ of D's
    diagonal (which contains the ray bounds, padded by ~10⁻⁶), the measured slope on B'
    (:func:`measure_slope`) and the local bound on B' (:func:`certify_local_lipschitz`)."""
    t0 = time.perf_counter()
    sb = certify_surface_box(net)
    grow = 1e-3 * float(np.linalg.norm(net.domain_hi - net.domain_lo))
    llo, lhi = sb["lo"] - grow, sb["hi"] + grow
    measured = measure_slope(net, llo, lhi)
    loc = certify_local_lipschitz(net, llo, lhi, measured)
    return {"surface_lo": sb["lo"], "surface_hi": sb["hi"], "local_lo": llo, "local_hi": lhi, "measured": measured,
            "local_L": loc["L"], "local_lower": loc["lower"], "local_cells": loc["cells"], "local_rounds": loc["rounds"],
            "surface_cells_inside": sb["cells_inside"], "surface_cells_outside": sb["cells_outside"],
            "seconds": time.perf_counter() - t0}


# -- the scene -------------------------------------------------------------------------------

class NeuralSDF(Field):
    """A stored softplus MLP fitted to a mesh's SDF (module doc); ``lipschitz`` ∈ :data:`MODES`."""

    kind = "neural"

    def __init__(self, path: str | Path = DEFAULT, weights: dict | None = None, lipschitz: str = "spectral"):
        if lipschitz not in MODES:
            raise ValueError(f"lipschitz must be one of {MODES} (spectral: certified everywhere; local: certified "
                             f"on the domain box; measured: 1.05 × the largest sampled slope, not certified), "
                             f"got {lipschitz!r}")
        if weights is None:
            path = Path(path)
            if not path.exists():
                raise ValueError(f"neural SDF weights file {path} not found; run `python -m reference.make_neural_sdf`")
            with np.load(path) as f:
                weights = {k: f[k] for k in f.files}
        k = 1
        layers = []
        while f"W{k}" in weights:
            if f"b{k}" not in weights:
                raise ValueError(f"neural SDF weights have W{k} but no b{k}")
            W, b = np.asarray(weights[f"W{k}"], np.float64), np.asarray(weights[f"b{k}"], np.float64)
            fan_in = 3 if k == 1 else layers[-1][0].shape[1]
            if W.ndim != 2 or W.shape[0] != fan_in or b.shape != (W.shape[1],):
                raise ValueError(f"neural SDF layer {k}: W{k} {W.shape}, b{k} {b.shape} do not chain from width {fan_in}")
            layers.append((W, b))
            k += 1
        if len(layers) < 2 or layers[-1][0].shape[1] != 1:
            raise ValueError(f"neural SDF needs ≥ 2 layers W1, b1, … ending in width 1; got {len(layers)} layers")
        for key in ("beta", "domain_lo", "domain_hi"):
            if key not in weights:
                raise ValueError(f"neural SDF weights lack {key!r} (beta, domain_lo, domain_hi are stored with them)")
        self.layers = tuple(layers)
        self.beta = float(weights["beta"])
        self.domain_lo = np.asarray(weights["domain_lo"], np.float64).reshape(3)
        self.domain_hi = np.asarray(weights["domain_hi"], np.float64).reshape(3)
        if not (self.beta > 0 and math.isfinite(self.beta)) or not np.all(self.domain_lo < self.domain_hi):
            raise ValueError(f"neural SDF needs beta > 0 and domain_lo < domain_hi, got beta={self.beta}, "
                             f"domain {self.domain_lo.tolist()}–{self.domain_hi.tolist()}")
        self.lipschitz_mode = lipschitz
        # a certificate stored with the weights (checked against their hash before use)
        self._stored_cert = None
        if "cert_sha" in weights and all(f"cert_{k}" in weights for k in CERT_KEYS):
            self._stored_cert = {k: np.asarray(weights[f"cert_{k}"]) for k in CERT_KEYS} | {"sha": str(weights["cert_sha"])}

    # -- structure ---------------------------------------------------------------------------
    def own_params(self):
        out = {}
        for k, (W, b) in enumerate(self.layers, 1):
            out[f"W{k}"], out[f"b{k}"] = W, b
        return out

    def _stored(self) -> dict:
        out = {"beta": self.beta, "domain_lo": self.domain_lo, "domain_hi": self.domain_hi}
        if self._stored_cert is not None:
            out |= {f"cert_{k}": v for k, v in self._stored_cert.items()}
        return out

    def _rebuild(self, own, children):
        w = {name: np.reshape(np.asarray(v, np.float64), np.shape(self.own_params()[name])) for name, v in own.items()}
        return NeuralSDF(weights={**w, **self._stored()}, lipschitz=self.lipschitz_mode)

    def with_lipschitz(self, lipschitz: str) -> "NeuralSDF":
        """The same network with another Lipschitz mode (certificates already computed are shared)."""
        other = NeuralSDF(weights={**self.own_params(), **self._stored()}, lipschitz=lipschitz)
        for name in ("spectral_bound", "certificate"):
            if name in self.__dict__:
                other.__dict__[name] = self.__dict__[name]
        return other

    def _static_spec(self) -> dict:
        return {"beta": self.beta, "domain_lo": self.domain_lo.tolist(), "domain_hi": self.domain_hi.tolist(),
                "lipschitz": self.lipschitz_mode, "L": self.lipschitz_bound}

    # -- bounds --------------------------------------------------------------------------------
    def weights_sha(self) -> str:
        """SHA-256 of the float64 weights, β and the domain: what a stored certificate is for."""
        h = hashlib.sha256()
        for W, b in self.layers:
            h.update(np.ascontiguousarray(W).tobytes())
            h.update(np.ascontiguousarray(b).tobytes())
        h.update(np.array([self.beta, *self.domain_lo, *self.domain_hi]).tobytes())
        return h.hexdigest()

    @functools.cached_property
    def certificate(self) -> dict:
        """:func:`certify` of these weights: the one stored with them (``cert_*`` in the weights
        file, for the same :meth:`weights_sha`; ``tests/test_neural_reference.py`` recomputes it),
        else computed now (seconds to tens of seconds)."""
        stored = self._stored_cert
        if stored is not None and stored.get("sha") == self.weights_sha():
            return {k: stored[k] for k in CERT_KEYS}
        return certify(self)

    @functools.cached_property
    def spectral_bound(self) -> float:
        """∏ₖ ‖Wₖ‖₂ (sup σ' = 1), rounded up by a relative 1e-12 (the SVD's error is ~ε‖W‖)."""
        return float(np.prod([np.linalg.norm(W, 2) for W, _ in self.layers])) * (1 + 1e-12)

    @property
    def measured_slope(self) -> float:
        """The largest |∇φ| found on the local box (:func:`measure_slope`): a lower bound of the
        true supremum, not an upper one."""
        return float(self.certificate["measured"])

    @property
    def local_bound(self) -> float:
        """The certified bound of |∇φ| on the local box (:func:`certify_local_lipschitz`)."""
        return float(self.certificate["local_L"])

    @property
    def surface_box(self) -> tuple[np.ndarray, np.ndarray]:
        """The certified box B ⊂ domain containing {φ ≤ 0} (:func:`certify_surface_box`)."""
        return np.asarray(self.certificate["surface_lo"]), np.asarray(self.certificate["surface_hi"])

    @property
    def local_box(self) -> tuple[np.ndarray, np.ndarray]:
        """The box on which the local and measured bounds are stated: B grown by 10⁻³ of the
        domain's diagonal (it contains the ray bounds)."""
        return np.asarray(self.certificate["local_lo"]), np.asarray(self.certificate["local_hi"])

    @property
    def lipschitz_bound(self) -> float:
        if self.lipschitz_mode == "spectral":
            return self.spectral_bound
        if self.lipschitz_mode == "local":
            return self.local_bound
        return MEASURED_FACTOR * self.measured_slope

    @property
    def domain_text(self) -> str:
        """SceneInfo.domain of the local and measured modes: the local box, in words."""
        lo, hi = self.local_box
        f = lambda v: "(" + ", ".join(f"{x:.6f}" for x in v) + ")"
        return f"box {f(lo)} <= x <= {f(hi)}"

    @property
    def info(self):
        return SceneInfo(exact_sdf=False, lipschitz=self.lipschitz_bound, distance_bound=False, smooth=True,
                         exact_hits=False, exact_normals=True, exact_curvature=True, exact_hit_param_grad=True,
                         domain=None if self.lipschitz_mode == "spectral" else self.domain_text)

    def bounding_sphere(self):
        lo, hi = self.surface_box
        return 0.5 * (lo + hi), float(0.5 * np.linalg.norm(hi - lo))

    def domain_hulls(self):
        """(the certified box B, the box the local and measured bounds are stated on) as exact
        box SDFs (B grown by 10⁻³ of the domain's diagonal: strictly inside); None for the
        spectral bound, which holds everywhere."""
        from .primitives import Box
        from .transform import Transform

        if self.lipschitz_mode == "spectral":
            return None
        boxes = (self.surface_box, self.local_box)
        return tuple(Transform(Box(half_size=tuple(0.5 * (hi - lo))), translation=0.5 * (lo + hi)) for lo, hi in boxes)

    def ray_bounds(self, xp, o, d):
        """The slab test of the certified box B (:attr:`surface_box`), padded against rounding
        (:func:`reference.raybounds.box_chord`)."""
        from .arrays import const

        lo, hi = self.surface_box
        centre = 0.5 * (lo + hi)
        return box_chord(xp, o - const(xp, o, centre), d, 0.5 * (hi - lo), float(np.linalg.norm(hi - lo)))

    @functools.cached_property
    def rounding_gain(self) -> float:
        """A forward error bound E of φ's float64 evaluation on the domain (Higham §3.1 through
        each layer: |δz| ≤ |W|ᵀ|δa| + (n + 3)ε(|W|ᵀ|a| + |b|), |δa| ≤ |δz| + 8ε(|a| + |z|)), in units
        of what the Lipschitz check allows in depth for φ's rounding, 16ε·scale with scale =
        |centre| + radius of the bounding ball, at this mode's L: gain = max(1, 2E/(16ε·scale·L))."""
        lo, hi = self.domain_lo, self.domain_hi
        amag = np.maximum(np.abs(lo), np.abs(hi))  # |x| per coordinate over the domain
        err = np.zeros(3)
        for i, (W, b) in enumerate(self.layers):
            aW = np.abs(W)
            zmag = amag @ aW + np.abs(b)
            err = err @ aW + (W.shape[0] + 3) * EPS * zmag
            if i < len(self.layers) - 1:
                amag = zmag + math.log(2) / self.beta
                err = err + 8 * EPS * (amag + zmag)
        c, rad = self.bounding_sphere()
        scale = float(np.linalg.norm(c)) + rad
        return max(1.0, 2 * float(err[0]) / (16 * EPS * scale * self.lipschitz_bound))

    # -- evaluation ----------------------------------------------------------------------------
    def _eval(self, x, xp, cursor):
        # points as one (m, 3) matrix: numpy's matmul of a stack of matrices is ~7× slower than
        # the one 2-D product (no single BLAS call)
        lead = tuple(x.shape[:-1])
        h = xp.reshape(x, (-1, 3))
        n = len(self.layers)
        for k, (W, b) in enumerate(self.layers):
            Wt, bt = cursor.take(W), cursor.take(b)
            h = xp.matmul(h, Wt) + bt
            if k < n - 1:
                h = softplus(xp, h, self.beta)
        return xp.reshape(h[:, 0], lead)

    def _forward(self, x):
        """Pre-activations z₁ … z_{K−1} and φ at points (n, 3), numpy float64."""
        zs, h = [], x
        for W, b in self.layers[:-1]:
            z = h @ W + b
            zs.append(z)
            h = softplus(np, z, self.beta)
        W, b = self.layers[-1]
        return zs, (h @ W + b)[:, 0]

    def gradient_norm(self, x):
        """|∇φ| at points (n, 3) (back-propagation, numpy), in chunks."""
        out = []
        for s in range(0, x.shape[0], 20_000):
            zs, _ = self._forward(x[s:s + 20_000])
            g = self.layers[-1][0][:, 0]
            for (W, _), z in zip(reversed(self.layers[:-1]), reversed(zs)):
                g = (g * logistic(self.beta * z)) @ W.T
            out.append(np.linalg.norm(g, axis=-1))
        return np.concatenate(out) if out else np.zeros(0)

    def gradient_hessian(self, x):
        """(φ, ∇φ (n, 3), Hessian (n, 3, 3)) in closed form: forward mode through the layers,
        J_{k+1} = W_{k+1}ᵀ(σ'(zₖ) ⊙ Jₖ), T_{k+1} = W_{k+1}ᵀ(σ''(zₖ) Jₖ⊗Jₖ + σ'(zₖ) Tₖ), J₁ = W₁ᵀ, T₁ = 0."""
        x = _points(x)
        n = x.shape[0]
        W1, b1 = self.layers[0]
        z = x @ W1 + b1
        J = np.broadcast_to(W1.T, (n,) + W1.T.shape)  # (n, H, 3): ∂z/∂x
        T = None  # (n, H, 3, 3): ∂²z/∂x², zero for the first layer
        for W, b in self.layers[1:]:
            s = logistic(self.beta * z)
            s1 = self.beta * s * (1 - s)
            a = softplus(np, z, self.beta)
            Ja = s[:, :, None] * J
            Ta = s1[:, :, None, None] * J[:, :, :, None] * J[:, :, None, :]
            if T is not None:
                Ta = Ta + s[:, :, None, None] * T
            z = a @ W + b
            J = np.einsum("hk,nhi->nki", W, Ja)
            T = np.einsum("hk,nhij->nkij", W, Ta)
        return z[:, 0], J[:, 0, :], T[:, 0]

    def _jet(self, x):
        """φ, ∇φ and ∂φ/∂θ by back-propagation: δ_K = 1, δₖ = (δ_{k+1} W_{k+1}ᵀ) ⊙ σ'(zₖ),
        ∂φ/∂Wₖ = a_{k−1} ⊗ δₖ, ∂φ/∂bₖ = δₖ (a₀ = x), ∇φ = δ₁ W₁ᵀ."""
        zs, phi = self._forward(x)
        acts = [x] + [softplus(np, z, self.beta) for z in zs]
        n = x.shape[0]
        delta = np.ones((n, 1))
        parts = []
        for k in range(len(self.layers) - 1, -1, -1):
            W, _ = self.layers[k]
            parts.append(delta)
            parts.append(np.einsum("ni,nj->nij", acts[k], delta).reshape(n, -1))
            if k > 0:
                delta = (delta @ W.T) * logistic(self.beta * zs[k - 1])
        grad = delta @ self.layers[0][0].T
        return phi, grad, np.concatenate(parts[::-1], axis=1)

    def curvatures_exact(self, x):
        """Principal curvatures from the closed-form ∇φ and Hessian (:func:`principal_from_hessian`)."""
        _, g, H = self.gradient_hessian(x)
        return principal_from_hessian(g, H)

    def first_hit(self, o, d, t_min: float = 0.0, t_max: float = 10.0):
        from .numerical import first_hit_numeric

        return first_hit_numeric(self, _points(o, "o"), _points(d, "d"), t_min, t_max)[0]
