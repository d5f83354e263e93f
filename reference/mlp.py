"""A small MLP field with stored weights, shared bit for bit by every backend.

φ(x) = W₃ᵀ σ(W₂ᵀ σ(W₁ᵀ x + b₁) + b₂) + b₃, written as row-vector products
``σ(σ(x @ W1 + b1) @ W2 + b2) @ W3 + b3`` with ``xp.matmul``; weights from
``reference/data/mlp_blob.npz`` (made by :mod:`reference.make_mlp`).

Activation σ(z) = z/√(1 + z²) (the "inverse square root unit"): smooth (C^∞, so normals,
Newton steps and curvature are well defined), |σ'(z)| = (1 + z²)^{−3/2} ≤ 1 with equality at
z = 0, so sup|σ'| = 1 exactly; and it uses only +, ×, ÷ and √, which IEEE 754 rounds correctly
in every library — unlike tanh or softplus, whose libm/SLEEF/XLA implementations differ in the
last bits.  What can still differ between libraries is the summation order inside matmul.

Lipschitz bound (lecture eqs. 4–6): L = ‖W₁‖₂‖W₂‖₂‖W₃‖₂ · (sup|σ'|)² with the exact spectral
norms (largest *singular* value, by SVD; the lecture's "largest eigenvalue" is true only for
symmetric positive semi-definite matrices).  θ = (W1, b1, W2, b2, W3, b3) flattened row-major.
Hits come from the numerical reference (:mod:`reference.numerical`), certified by L.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from .scene import Field, SceneInfo, _points

DEFAULT = Path(__file__).with_name("data") / "mlp_blob.npz"
_NAMES = ("W1", "b1", "W2", "b2", "W3", "b3")


def act(xp, z):
    """σ(z) = z/√(1 + z²)."""
    return z / xp.sqrt(1.0 + z * z)


def act_prime(z):
    """σ'(z) = (1 + z²)^{−3/2} (numpy)."""
    return (1.0 + z * z) ** -1.5


class MLPField(Field):
    kind = "mlp"

    def __init__(self, path: str | Path = DEFAULT, weights: dict | None = None):
        if weights is None:
            path = Path(path)
            if not path.exists():
                raise ValueError(f"MLP weights file {path} not found; run `python -m reference.make_mlp`")
            with np.load(path) as f:
                weights = {k: f[k] for k in _NAMES}
        missing = [k for k in _NAMES if k not in weights]
        if missing:
            raise ValueError(f"MLP weights lack {missing}; expected {_NAMES}")
        self.weights = {k: np.asarray(weights[k], np.float64) for k in _NAMES}
        W1, W2, W3 = (self.weights[k] for k in ("W1", "W2", "W3"))
        if W1.shape[0] != 3 or W2.shape[0] != W1.shape[1] or W3.shape != (W2.shape[1], 1):
            raise ValueError(f"MLP weight shapes {[self.weights[k].shape for k in _NAMES]} do not chain 3 → H1 → H2 → 1")

    def own_params(self):
        return dict(self.weights)

    @functools.cached_property
    def lipschitz_bound(self) -> float:
        return float(np.prod([np.linalg.norm(self.weights[k], 2) for k in ("W1", "W2", "W3")]))

    @property
    def info(self):
        return SceneInfo(exact_sdf=False, lipschitz=self.lipschitz_bound, distance_bound=False, smooth=True,
                         exact_hits=False, exact_normals=True, exact_curvature=False, exact_hit_param_grad=True)

    def _rebuild(self, own, children):
        return MLPField(weights={k: np.reshape(own[k], self.weights[k].shape) for k in _NAMES})

    def _eval(self, x, xp, cursor):
        W1, b1, W2, b2, W3, b3 = (cursor.take(self.weights[k]) for k in _NAMES)
        h = act(xp, xp.matmul(x, W1) + b1)
        h = act(xp, xp.matmul(h, W2) + b2)
        return (xp.matmul(h, W3) + b3)[..., 0]

    def _jet(self, x):
        """Back-propagation in closed form: δ₂ = W₃ ⊙ σ'(z₂), δ₁ = (δ₂ W₂ᵀ) ⊙ σ'(z₁),
        ∇φ = δ₁ W₁ᵀ; ∂φ/∂W₁ = x ⊗ δ₁, ∂φ/∂b₁ = δ₁, ∂φ/∂W₂ = a₁ ⊗ δ₂, ∂φ/∂b₂ = δ₂,
        ∂φ/∂W₃ = a₂, ∂φ/∂b₃ = 1."""
        w = self.weights
        z1 = x @ w["W1"] + w["b1"]
        a1 = act(np, z1)
        z2 = a1 @ w["W2"] + w["b2"]
        a2 = act(np, z2)
        phi = (a2 @ w["W3"] + w["b3"])[:, 0]
        d2 = w["W3"][:, 0] * act_prime(z2)
        d1 = (d2 @ w["W2"].T) * act_prime(z1)
        grad = d1 @ w["W1"].T
        n = x.shape[0]
        dth = np.concatenate([np.einsum("ni,nj->nij", x, d1).reshape(n, -1), d1,
                              np.einsum("ni,nj->nij", a1, d2).reshape(n, -1), d2, a2, np.ones((n, 1))], axis=1)
        return phi, grad, dth

    def first_hit(self, o, d, t_min: float = 0.0, t_max: float = 10.0):
        from .numerical import first_hit_numeric

        return first_hit_numeric(self, _points(o, "o"), _points(d, "d"), t_min, t_max)[0]
