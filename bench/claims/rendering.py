"""The lecture's discrete volume rendering, eqs. (9)–(10), written exactly as stated.

    C(r) = Σ_{i=1..N} T_i α_i ρ(x_i),   T_i = Π_{j<i} (1 − α_j),   α_i = 1 − exp(−σ(x_i) δ_i)

(the lecture's "σ(x_i) = 1 − exp(−σ_θ(x_i)δ_i)", density → occupancy).  No background term: light
that is not absorbed contributes nothing, as in eq. (9).  This is the object of study of claims 8–10,
so it lives here, written with the lecture's cumulative product; the continuous integral it discretises
is ``reference.rendering.render_exact`` (claims 8 and 10 compare with it).
"""

from __future__ import annotations

import numpy as np


def composite(alpha: np.ndarray, colour: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(C, T_{N+1}) for opacities ``alpha`` (rays, N) and colours ``colour`` of shape (rays, N) (scalar) or
    (rays, N, channels) (e.g. RGB), front to back; C has shape (rays,) or (rays, channels)."""
    alpha = np.asarray(alpha, float)
    colour = np.asarray(colour, float)
    if colour.shape[: alpha.ndim] != alpha.shape or colour.ndim > alpha.ndim + 1:
        raise ValueError(f"alpha {alpha.shape} and colour {colour.shape} must have shapes (rays, N) and "
                         "(rays, N) or (rays, N, channels)")
    if np.any((alpha < 0) | (alpha > 1)):
        raise ValueError("alpha must lie in [0, 1]; clip the opacities or fix the density model")
    trans = np.cumprod(np.concatenate([np.ones(alpha.shape[:-1] + (1,)), 1.0 - alpha], axis=-1), axis=-1)
    w = trans[..., :-1] * alpha
    if colour.ndim > alpha.ndim:
        w = w[..., None]
    return np.sum(w * colour, axis=alpha.ndim - 1), trans[..., -1]


def window_samples(t_s: np.ndarray, delta: float, n: int):
    """N sample depths at the midpoints of N equal sections of [t_s − Δ, t_s + Δ] (so every sample is
    within Δ of the surface, the lecture's definition of Δ), with section ends and lengths."""
    edges = t_s[:, None] + np.linspace(-delta, delta, n + 1)[None, :]
    mids = 0.5 * (edges[:, :-1] + edges[:, 1:])
    return mids, edges[:, :-1], edges[:, 1:], np.diff(edges, axis=1)
