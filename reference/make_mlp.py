"""Generate the stored MLP field ``reference/data/mlp_blob.npz`` (seeded, deterministic).

    python -m reference.make_mlp            # rewrites the file; the committed file is the truth

Architecture 3 → 16 → 16 → 1 with the activation σ(z) = z/√(1 + z²) (see
:mod:`reference.mlp` for why).  The two hidden layers are random (seeded Gaussian, scaled
1.5/√fan_in); the output layer is the least-squares fit of the random features to the SDF of a
sphere of radius 0.8 on points in the ball of radius 2 (random-feature regression, a linear
solve), so the zero set is a closed, slightly wobbly blob around the origin.  Weights are
float64; the file is ~3 KB.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

PATH = Path(__file__).with_name("data") / "mlp_blob.npz"
SEED = 20215  # the first of seeds 20211… whose zero set encloses |x| ≤ 0.4 and lies inside |x| < 2


def act(z):
    return z / np.sqrt(1.0 + z * z)


def make(seed: int = SEED, hidden: int = 16) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    W1 = rng.normal(size=(3, hidden)) * 1.5 / np.sqrt(3)
    b1 = rng.normal(size=hidden) * 0.5
    W2 = rng.normal(size=(hidden, hidden)) * 1.5 / np.sqrt(hidden)
    b2 = rng.normal(size=hidden) * 0.5
    x = rng.normal(size=(4000, 3))
    x *= (2.0 * rng.uniform(size=(4000, 1)) ** (1 / 3)) / np.linalg.norm(x, axis=1, keepdims=True)
    feats = act(act(x @ W1 + b1) @ W2 + b2)
    A = np.concatenate([feats, np.ones((x.shape[0], 1))], axis=1)
    coef, *_ = np.linalg.lstsq(A, np.linalg.norm(x, axis=1) - 0.8, rcond=None)
    return {"W1": W1, "b1": b1, "W2": W2, "b2": b2, "W3": coef[:-1, None], "b3": coef[-1:]}


def main() -> None:
    PATH.parent.mkdir(exist_ok=True)
    np.savez(PATH, **make())
    print(f"wrote {PATH} ({PATH.stat().st_size} bytes)")


if __name__ == "__main__":
    main()
