"""Train the stored neural SDF ``reference/data/neural_blob.npz`` (seeded; CPU, about two minutes).

    python -m reference.make_neural_sdf       # rewrites the file; the committed file is the truth

An IDR-style MLP (Yariv et al., "Multiview Neural Surface Reconstruction by Disentangling
Geometry and Appearance", NeurIPS 2020) 3 → 64 → 64 → 1 with the β-softplus activation
σ(z) = log(1 + e^{βz})/β, β = 100, fitted to the exact signed distance of the stored ``blob``
mesh (:class:`reference.mesh.MeshSDF`, a 5120-face wavy sphere):

* Geometric initialisation (Atzmon & Lipman, "SAL: Sign Agnostic Learning of Shapes from Raw
  Data", CVPR 2020, §4; as in IDR's code): hidden weights N(0, 2/fan_out), hidden biases 0, the
  output weights N(√π/√fan_in, 10⁻⁸) and the output bias −r₀, so that the initial network is
  close to |x| − r₀, a sphere of radius r₀ = 1.
* Samples (fixed pool, drawn once): points on the mesh (uniform by area) displaced by Gaussian
  noise of standard deviation 0.01 and 0.08 (the "near-surface" samples of SAL/IGR), and
  points uniform in the training box (the scene's domain padded by 0.2); targets are the
  mesh's exact float64 signed distances.
* Loss: mean |φ_net − φ_mesh| (L1, as DeepSDF/IDR fit SDF values) + λ·mean((|∇φ_net| − 1)²)
  (the eikonal term of IGR, Gropp et al. 2020), λ = 0.1, on minibatches of 4096 from the pool;
  Adam, learning rate 2·10⁻³ decayed by cosine to 2·10⁻⁵ over 3000 steps.
* Trained in float32 on one thread (float64 costs 3× the time on a CPU; one thread so that a
  rerun with the same torch build gives the same bits); the weights are stored as float64 arrays
  (the float32 values, exactly), and the scene evaluates them in float64: the stored network is
  the truth, however it was trained.  Arrays ``W1 (3, 64), b1 (64,), W2 (64, 64), b2, W3 (64, 1), b3 (1,)`` in the
  row-vector convention φ = σ(σ(x W1 + b1) W2 + b2) W3 + b3, with ``beta`` and the domain box
  ``domain_lo``, ``domain_hi`` (the mesh's bounding box padded by :data:`DOMAIN_PAD`), where
  :class:`reference.neural.NeuralSDF` looks for the surface; and the certificate of
  :func:`reference.neural.certify` (the box containing the surface, the local and the measured
  Lipschitz bounds), ``cert_*``, with the SHA-256 of the weights it is for, so that loading the
  network costs nothing (the scene recomputes it for any other weights; a test recomputes it).

The script prints the fit error near the surface (on held-out points within 0.05 of the mesh).
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

PATH = Path(__file__).with_name("data") / "neural_blob.npz"
SEED = 20260418
BETA = 100.0
HIDDEN = (64, 64)
DOMAIN_PAD = 0.3  # the domain box: the mesh's bounding box grown by this on every side
TRAIN_PAD = 0.2  # uniform training samples fill the domain grown by this
STEPS = 3000
BATCH = 4096
EIKONAL = 0.1


def surface_samples(mesh, n: int, rng) -> np.ndarray:
    """``n`` points uniform by area on the mesh's triangles (seeded)."""
    V, F = mesh.vertices, mesh.faces
    area = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    face = rng.choice(F.shape[0], n, p=area / area.sum())
    u, v = rng.uniform(size=(2, n))
    flip = u + v > 1  # fold the square onto the triangle
    u, v = np.where(flip, 1 - u, u), np.where(flip, 1 - v, v)
    a, b, c = (V[F[face, k]] for k in range(3))
    return a + u[:, None] * (b - a) + v[:, None] * (c - a)


def samples(mesh, lo, hi, rng, n_surface: int, n_uniform: int) -> tuple[np.ndarray, np.ndarray]:
    """The training pool: near-surface and uniform points with the mesh's exact SDF."""
    p = surface_samples(mesh, n_surface, rng)
    sigma = np.where(np.arange(n_surface) % 2 == 0, 0.01, 0.08)[:, None]
    near = p + sigma * rng.normal(size=p.shape)
    uni = rng.uniform(lo - TRAIN_PAD, hi + TRAIN_PAD, size=(n_uniform, 3))
    x = np.concatenate([near, uni])
    return x, mesh.value(x)


def init_network(torch, gen, r0: float = 1.0):
    """Geometric initialisation (SAL §4) of the layers 3 → HIDDEN → 1 (drawn in float64)."""
    dims = (3, *HIDDEN, 1)
    params = []
    for k in range(len(dims) - 1):
        fan_in, fan_out = dims[k], dims[k + 1]
        if k == len(dims) - 2:
            W = math.sqrt(math.pi) / math.sqrt(fan_in) + 1e-4 * torch.randn(fan_in, fan_out, generator=gen, dtype=torch.float64)
            b = torch.full((fan_out,), -r0, dtype=torch.float64)
        else:
            W = math.sqrt(2.0) / math.sqrt(fan_out) * torch.randn(fan_in, fan_out, generator=gen, dtype=torch.float64)
            b = torch.zeros(fan_out, dtype=torch.float64)
        params += [W.requires_grad_(), b.requires_grad_()]
    return params


def forward(torch, params, x):
    h = x
    n = len(params) // 2
    for k in range(n):
        h = h @ params[2 * k] + params[2 * k + 1]
        if k < n - 1:
            h = torch.nn.functional.softplus(h, beta=BETA)
    return h[..., 0]


def train(seed: int = SEED, steps: int = STEPS, log=print) -> dict[str, np.ndarray]:
    import torch

    from .mesh import MeshSDF

    torch.set_num_threads(1)
    mesh = MeshSDF.load("blob")
    lo = mesh.vertices.min(axis=0) - DOMAIN_PAD
    hi = mesh.vertices.max(axis=0) + DOMAIN_PAD
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    x_np, f_np = samples(mesh, lo, hi, rng, 200_000, 100_000)
    log(f"samples: {x_np.shape[0]} points with mesh SDF in {time.perf_counter() - t0:.1f} s")
    gen = torch.Generator().manual_seed(seed)
    params = [p.detach().to(torch.float32).requires_grad_() for p in init_network(torch, gen)]
    x_all, f_all = torch.from_numpy(x_np).to(torch.float32), torch.from_numpy(f_np).to(torch.float32)
    opt = torch.optim.Adam(params, lr=2e-3)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=steps, eta_min=2e-5)
    t0 = time.perf_counter()
    for step in range(steps):
        idx = torch.randint(0, x_all.shape[0], (BATCH,), generator=gen)
        x = x_all[idx].requires_grad_()
        f = forward(torch, params, x)
        (g,) = torch.autograd.grad(f.sum(), x, create_graph=True)
        fit = (f - f_all[idx]).abs().mean()
        eik = ((g.norm(dim=-1) - 1.0) ** 2).mean()
        loss = fit + EIKONAL * eik
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        if step % 500 == 0 or step == steps - 1:
            log(f"step {step:5d}  L1 {fit.item():.2e}  eikonal {eik.item():.2e}  ({time.perf_counter() - t0:.0f} s)")
    out = {}
    for k in range(len(params) // 2):
        out[f"W{k + 1}"] = params[2 * k].detach().numpy().astype(np.float64)
        out[f"b{k + 1}"] = params[2 * k + 1].detach().numpy().astype(np.float64)
    out.update(beta=np.float64(BETA), domain_lo=lo, domain_hi=hi, seed=np.int64(seed))
    return out


def fit_error(weights: dict, n: int = 20_000, seed: int = 1) -> dict[str, float]:
    """|φ_net − φ_mesh| on held-out points within 0.05 of the mesh (on it and displaced along
    Gaussian noise of σ = 0.02, clipped to |φ_mesh| ≤ 0.05), and on the surface itself."""
    from .mesh import MeshSDF
    from .neural import NeuralSDF

    mesh, net = MeshSDF.load("blob"), NeuralSDF(weights=weights)
    rng = np.random.default_rng(seed)
    p = surface_samples(mesh, n, rng)
    x = p + 0.02 * rng.normal(size=p.shape)
    fm = mesh.value(x)
    keep = np.abs(fm) <= 0.05
    e_near = np.abs(net.value(x[keep]) - fm[keep])
    e_surf = np.abs(net.value(p))
    return {"near_max": float(e_near.max()), "near_mean": float(e_near.mean()), "surface_max": float(e_surf.max()),
            "surface_mean": float(e_surf.mean()), "n_near": int(keep.sum())}


def write(weights: dict, path: Path = PATH) -> dict:
    """Certify ``weights`` (:func:`reference.neural.certify`: surface box, local and measured
    bounds) and save them with the certificate and the weights' hash."""
    from .neural import CERT_KEYS, NeuralSDF, certify

    net = NeuralSDF(weights=weights)
    cert = certify(net)
    path.parent.mkdir(exist_ok=True)
    np.savez(path, **weights, **{f"cert_{k}": np.asarray(cert[k]) for k in CERT_KEYS}, cert_sha=net.weights_sha())
    return cert


def main() -> None:
    t0 = time.perf_counter()
    w = train()
    print(f"trained in {time.perf_counter() - t0:.0f} s")
    cert = write(w)
    print(f"wrote {PATH} ({PATH.stat().st_size} bytes); certificate in {cert['seconds']:.0f} s: "
          f"local L {cert['local_L']:.4f}, measured slope {cert['measured']:.4f}")
    print("fit error:", fit_error(w))


if __name__ == "__main__":
    main()
