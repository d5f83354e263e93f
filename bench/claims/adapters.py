"""The one place where the claims obtain pieces owned by ``reference/`` and ``impls/``.

Everything a claim needs from another part of isobench goes through a function here, so that
when the reference branch (shapes, CSG, colour fields, density models, MLP field) and the impls
branch (root finders, gradients, renderers) land, each piece is switched in one place.  Until
then the stand-ins below are small float64 numpy formulas with their source; each says which
upstream object replaces it (``SWITCH:`` lines).

All functions take and return float64 numpy arrays; points have shape ``(..., 3)``.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from reference import Sphere

Array = np.ndarray


# -- shapes ---------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Shape:
    """An implicit function with what is known about it exactly.

    f:            φ(x), (..., 3) → (...); φ < 0 inside.
    exact_sdf:    φ is the signed distance.
    lipschitz:    a valid Lipschitz constant of φ on the ball |x| ≤ ``domain_radius`` (None: unknown).
    first_hit:    exact first crossing depth (o, d, t_min) → t (inf: miss), or None.
    curv_sum:     exact κ1 + κ2 at surface points (outward normal, sphere positive), or None.
    normal:       exact unit outward normal at surface points, computed independently of ∇φ, or None.
    closest:      exact closest surface point of x, or None.
    """

    name: str
    f: Callable[[Array], Array]
    exact_sdf: bool
    lipschitz: float | None = None
    domain_radius: float = np.inf
    first_hit: Callable | None = None
    curv_sum: Callable | None = None
    normal: Callable | None = None
    closest: Callable | None = None


def sphere_shape(radius: float = 1.0, center=(0.0, 0.0, 0.0)) -> Shape:
    """The reference :class:`reference.Sphere` (exact SDF |x − c| − r)."""
    s = Sphere(center=center, radius=radius)
    c = np.asarray(center, float)
    return Shape(
        name=f"sphere SDF |x−c|−{radius:g}", f=lambda x: s.value(np.asarray(x, float)), exact_sdf=True, lipschitz=1.0,
        first_hit=s.first_hit, curv_sum=lambda x: sum(s.curvatures_exact(x)), normal=s.normal_exact,
        closest=lambda x: c + radius * s.normal_exact(x),
    )


def algebraic_sphere_shape(radius: float = 1.0, domain_radius: float = 4.0) -> Shape:
    """The lecture's φ(x) = |x|² − r² (not an SDF).  |∇φ| = 2|x| so L = 2R on |x| ≤ R.

    SWITCH: reference's algebraic sphere once ``ref`` lands.
    """
    s = Sphere(radius=radius)
    return Shape(
        name=f"algebraic sphere |x|²−{radius**2:g}", f=lambda x: np.sum(np.asarray(x, float) ** 2, axis=-1) - radius**2,
        exact_sdf=False, lipschitz=2.0 * domain_radius, domain_radius=domain_radius, first_hit=s.first_hit,
        curv_sum=lambda x: sum(s.curvatures_exact(x)), normal=s.normal_exact,
        closest=lambda x: radius * s.normal_exact(x),
    )


def scaled_shape(base: Shape, k: float) -> Shape:
    """k·φ: same surface, |∇(kφ)| = k, Lipschitz k·L.  SWITCH: reference's scaled SDF."""
    return dataclasses.replace(
        base, name=f"{k:g}·({base.name})", f=lambda x: k * base.f(x), exact_sdf=base.exact_sdf and k == 1.0,
        lipschitz=None if base.lipschitz is None else abs(k) * base.lipschitz,
    )


def torus_shape(R: float = 1.0, r: float = 0.4) -> Shape:
    """Torus about the z axis, φ = √((√(x²+y²) − R)² + z²) − r (exact SDF; Quilez, "distance
    functions").  Principal curvatures at a surface point with ρ = √(x²+y²): κ_tube = 1/r and
    κ_ring = (ρ − R)/(r ρ) (= cos v/(R + r cos v)), positive where convex (do Carmo §3-3).

    SWITCH: reference's Torus (with its exact hits) once ``ref`` lands.
    """

    def f(x):
        x = np.asarray(x, float)
        rho = np.hypot(x[..., 0], x[..., 1])
        return np.hypot(rho - R, x[..., 2]) - r

    def curv_sum(x):
        rho = np.hypot(x[..., 0], x[..., 1])
        return 1.0 / r + (rho - R) / (r * rho)

    def normal(x):
        x = np.asarray(x, float)
        rho = np.hypot(x[..., 0], x[..., 1])
        ring = np.stack([R * x[..., 0] / rho, R * x[..., 1] / rho, np.zeros_like(rho)], axis=-1)
        v = x - ring
        return v / np.linalg.norm(v, axis=-1, keepdims=True)

    return Shape(name=f"torus SDF R={R:g} r={r:g}", f=f, exact_sdf=True, lipschitz=1.0, curv_sum=curv_sum,
                 normal=normal, closest=lambda x: x - f(x)[..., None] * normal(x))


def box_shape(half=(0.8, 0.5, 0.3)) -> Shape:
    """Axis-aligned box SDF |max(q, 0)| + min(max_i q_i, 0), q = |x| − b (Quilez).  SWITCH: reference Box."""
    b = np.asarray(half, float)

    def f(x):
        q = np.abs(np.asarray(x, float)) - b
        return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0)

    return Shape(name=f"box SDF half={tuple(b.tolist())}", f=f, exact_sdf=True, lipschitz=1.0)


def ellipsoid_shape(axes=(1.0, 0.7, 0.5)) -> Shape:
    """Quadric q(x) = Σ x_i²/a_i² − 1 (not an SDF).  Exact normal from the parametrisation
    x = (a cos u sin v, b sin u sin v, c cos v): n ∝ ∂x/∂u × ∂x/∂v, computed without ∇q.

    SWITCH: reference's ellipsoid quadric.
    """
    a = np.asarray(axes, float)

    def f(x):
        return np.sum((np.asarray(x, float) / a) ** 2, axis=-1) - 1.0

    def normal(x):
        x = np.asarray(x, float)
        u = np.arctan2(x[..., 1] / a[1], x[..., 0] / a[0])
        v = np.arccos(np.clip(x[..., 2] / a[2], -1, 1))
        xu = np.stack([-a[0] * np.sin(u) * np.sin(v), a[1] * np.cos(u) * np.sin(v), 0 * u], -1)
        xv = np.stack([a[0] * np.cos(u) * np.cos(v), a[1] * np.sin(u) * np.cos(v), -a[2] * np.sin(v)], -1)
        n = np.cross(xu, xv)
        n = n / np.linalg.norm(n, axis=-1, keepdims=True)
        return np.where(np.sum(n * x, -1, keepdims=True) < 0, -n, n)  # outward

    return Shape(name=f"ellipsoid quadric axes={tuple(a.tolist())}", f=f, exact_sdf=False, normal=normal)


# -- CSG (SWITCH: reference Union/Intersection/Complement/Difference nodes) -----------------------

CSG_OPS: dict[str, Callable[[Array, Array], Array]] = {
    "union min(φ1,φ2)": np.minimum,
    "intersection max(φ1,φ2)": np.maximum,
    "complement −φ1": lambda a, b: -a,
    "difference max(φ1,−φ2)": lambda a, b: np.maximum(a, -b),
}


# -- colour field (SWITCH: reference's colour field with its Lipschitz constant) ------------------


def colour_field(gamma: float, axis=(0.6, 0.0, 0.8), offset: float = 0.5) -> Callable[[Array], Array]:
    """Scalar colour ρ(x) = offset + ½ sin(2γ a·x), |a| = 1: Lipschitz constant exactly γ."""
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    return lambda x: offset + 0.5 * np.sin(2.0 * gamma * (np.asarray(x, float) @ a))


# -- density models along a ray (SWITCH: reference/rendering.py density models) ------------------


def _sigmoid(z):
    return 0.5 * (1.0 + np.tanh(0.5 * z))  # overflow-free logistic


def density_alphas(model: str, phi_mid: Array, phi_lo: Array, phi_hi: Array, delta: Array, s: float) -> Array:
    """Discrete opacities α_i of the samples of one or more rays for a density model.

    phi_mid: φ at the sample points t_i; phi_lo/phi_hi: φ at the section ends t_i ∓ δ_i/2;
    δ_i: section lengths; s: sharpness (inverse length).

    * ``occupancy``  (UNISURF, Oechsle et al. 2021; the lecture's σ(x_i)): α_i = sigmoid(−s φ_i).
    * ``logistic``   (NeRF-style density from an SDF): σ = s·sigmoid(−s φ), α_i = 1 − exp(−σ_i δ_i).
    * ``laplace``    (VolSDF, Yariv et al. 2021): σ = s·Ψ(−φ), Ψ the CDF of Laplace(0, 1/s),
      α_i = 1 − exp(−σ_i δ_i).
    * ``neus``       (Wang et al. 2021, eq. 13): α_i = max((Φ(s φ_lo) − Φ(s φ_hi)) / Φ(s φ_lo), 0)
      with Φ the logistic sigmoid.
    """
    if model == "occupancy":
        return _sigmoid(-s * phi_mid)
    if model == "logistic":
        return -np.expm1(-s * _sigmoid(-s * phi_mid) * delta)
    if model == "laplace":
        y = -phi_mid * s
        psi = np.where(y <= 0, 0.5 * np.exp(np.minimum(y, 0)), 1 - 0.5 * np.exp(-np.maximum(y, 0)))
        return -np.expm1(-s * psi * delta)
    if model == "neus":
        a, b = _sigmoid(s * phi_lo), _sigmoid(s * phi_hi)
        with np.errstate(divide="ignore", invalid="ignore"):
            al = np.where(a > 0, (a - b) / a, 0.0)
        return np.clip(al, 0.0, 1.0)
    raise ValueError(f"density model {model!r} unknown; use one of {DENSITY_MODELS}")


DENSITY_MODELS = ("occupancy", "logistic", "laplace", "neus")


# -- MLP field (SWITCH: reference's MLP field with stored weights) --------------------------------


@dataclasses.dataclass(frozen=True)
class MLP:
    """f(x) = W_L σ(… σ(W_1 x + b_1) …) + b_L with σ = tanh (sup|σ'| = 1)."""

    weights: tuple
    biases: tuple
    sup_dact: float = 1.0
    name: str = "tanh MLP 3-32-32-1 (seeded stand-in)"

    def value(self, x):
        h = np.asarray(x, float)
        for W, b in zip(self.weights[:-1], self.biases[:-1]):
            h = np.tanh(h @ W.T + b)
        return (h @ self.weights[-1].T + self.biases[-1])[..., 0]

    def grad(self, x):
        """∇f by the chain rule (backpropagation written out), shape (..., 3)."""
        h = np.asarray(x, float)
        ds = []
        for W, b in zip(self.weights[:-1], self.biases[:-1]):
            z = h @ W.T + b
            h = np.tanh(z)
            ds.append(1 - h**2)
        g = np.broadcast_to(self.weights[-1][0], h.shape)
        for W, d in zip(reversed(self.weights[:-1]), reversed(ds)):
            g = (g * d) @ W
        return g


def mlp_field(seed: int = 7, widths=(3, 32, 32, 1), scale: float = 1.5) -> MLP:
    """A seeded tanh MLP whose zero level set crosses the box [−1.5, 1.5]³ (its last bias is set so
    that φ's median over that box is 0).  SWITCH: the reference MLP field (stored weights)."""
    rng = np.random.default_rng(seed)
    Ws, bs = [], []
    for i, (m, n) in enumerate(zip(widths[:-1], widths[1:])):
        Ws.append(rng.normal(0, scale / np.sqrt(m), (n, m)))
        bs.append(rng.normal(0, 0.3, n))
    net = MLP(tuple(Ws), tuple(bs))
    probe = rng.uniform(-1.5, 1.5, (4096, 3))
    shift = np.median(net.value(probe))
    bs[-1] = bs[-1] - shift
    return MLP(tuple(Ws), tuple(bs))


# -- root finding through a backend (SWITCH: impls methods: bisection/newton/secant/hybrid) -------


def prepare_trace(scene, o: Array, d: Array, *, tol: float = 1e-12, max_steps: int = 4096, t_max: float = 10.0,
                  backend_id: str = "numpy"):
    """The backend's ``sphere_trace`` prepared on these rays: returns (run, to_numpy) where ``run()`` does
    the timed work and ``to_numpy(out)`` gives (t, status, evals) as float64/int numpy."""
    from impls import registry

    b = registry.resolve(backend_id)
    if isinstance(b, registry.Unavailable):
        raise RuntimeError(f"backend {backend_id} unavailable: {b.reason}")
    prep = b.prepare("sphere_trace", scene, o, d, t_min=0.0, t_max=t_max, tol=tol, max_steps=max_steps)

    def run():
        out = prep.run()
        b.synchronize(out)
        return out

    def to_numpy(out):
        res = prep.result(out)
        return res.t, res.status, res.evals

    return run, to_numpy

