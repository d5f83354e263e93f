"""Colour fields, density models and the continuous volume-rendering reference.

Everything a backend needs to render is written against the array API (namespace ``xp``), so
numpy, torch and jax use the *same* formulas; :func:`render_exact` is the float64 reference.

Density models, each with a sharpness s > 0 (units 1/length; the transition width is ~1/s):

* ``nerf``    σ(x) = s · sigm(−s φ(x)): a NeRF-style volume density that is a fixed monotone
  function of the field (NeRF itself learns σ freely; Mildenhall et al., ECCV 2020).
* ``unisurf`` occupancy o(x) = sigm(−s φ(x)) used directly as the discrete α_i (Oechsle et al.,
  ICCV 2021, eq. 5).  It has no continuous density (α does not scale with the step), so it has
  no continuous reference: :func:`render_exact` refuses it; compare it with :func:`composite`.
* ``neus``    Φ_s(φ) = sigm(s φ); discrete α_i = max((Φ_s(φ_i) − Φ_s(φ_{i+1}))/Φ_s(φ_i), 0);
  continuous opaque density σ(t) = max(−(dΦ_s/dt)/Φ_s, 0) = max(−s (1 − Φ_s(φ)) ∂φ/∂t, 0)
  (Wang et al., NeurIPS 2021, eqs. 10–13).
* ``volsdf``  σ(x) = α Ψ_β(−φ(x)) with α = 1/β = s and Ψ_β the CDF of the zero-mean Laplace
  distribution with scale β (Yariv et al., NeurIPS 2021, eq. 2–3).

Rendering (lecture eqs. 9–10): C = ∫ T(t) σ(t) ρ(x(t)) dt, T(t) = exp(−∫_{t_min}^t σ); its
discrete form C = Σ T_i α_i ρ_i, T_i = Π_{j<i} (1 − α_j), α_i = 1 − exp(−σ_i δ_i).
"""

from __future__ import annotations

import bisect
import dataclasses
import math
from typing import Any

import numpy as np

from .arrays import const
from .scene import Field, _points, check_point_output

MODELS = ("nerf", "unisurf", "neus", "volsdf")


def _check_model(model: str, sharpness: float) -> float:
    if model not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got {model!r}")
    s = float(sharpness)
    if not (math.isfinite(s) and s > 0):
        raise ValueError(f"sharpness must be a finite number > 0 (1/length), got {sharpness!r}")
    return s


# -- colour field ------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class SineColor:
    """ρ_c(x) = ½ + ½ sin(ω a_c·x + p_c), c = r, g, b; values in [0, 1].

    Jacobian J = ½ω diag(cos(·)) A, so ‖ρ(x) − ρ(y)‖₂ ≤ L |x − y| with L = ½ ω ‖A‖₂ (the
    spectral norm, computed exactly by SVD): :attr:`lipschitz`, the γ of lecture eq. 12.
    """

    frequency: float = 2.0
    directions: tuple = ((1.0, 0.0, 0.0), (0.0, 0.6, 0.8), (0.48, -0.6, 0.64))
    phases: tuple = (0.0, 1.0, 2.0)

    def __post_init__(self):
        if not (math.isfinite(self.frequency) and self.frequency > 0):
            raise ValueError(f"frequency must be a finite number > 0, got {self.frequency!r}")

    @property
    def lipschitz(self) -> float:
        return 0.5 * self.frequency * float(np.linalg.norm(np.asarray(self.directions, float), 2))

    def value(self, x: Any, xp: Any = np) -> Any:
        """ρ(x) of shape (..., 3) for points (..., 3)."""
        A = const(xp, x, np.asarray(self.directions, np.float64).T)
        p = const(xp, x, np.asarray(self.phases, np.float64))
        return 0.5 + 0.5 * xp.sin(self.frequency * xp.matmul(x, A) + p)

    __call__ = value


#: what a colour field's output of the wrong kind is told to do (CheckedColor)
_RHO_FIXES = {"lib": "(e.g. xp.sin, not np.sin)",
              "shape": "Return three channels per point (e.g. xp.stack([r, g, b], axis=-1)), in [0, 1]",
              "dtype": "Cast with xp.astype(rho, x.dtype)"}


class CheckedColor:
    """A user's colour field ρ with every output checked (``prepare`` wraps the ``color`` it is
    given): ``value(x, xp)`` must return an array of ``x``'s library of shape ``x.shape[:-1] + (3,)``
    and a real floating dtype (another precision is converted to ``x``'s).  Anything else is a
    :class:`reference.scene.FieldError` naming the field and the fix.  Unchecked, a field returning
    one value per point, or four channels, is broadcast against the samples or carried into the
    output, or fails deep inside a renderer with an error that names nothing.

    Equal (and hashing) as the field it wraps, so a kernel compiled for a field is reused for it.
    Cost: a few attribute comparisons per call; under ``jax.jit`` once, at trace time."""

    __slots__ = ("field",)

    def __init__(self, field):
        self.field = field

    def __eq__(self, other):
        return isinstance(other, CheckedColor) and (other.field is self.field or other.field == self.field)

    def __hash__(self):
        try:
            return hash(self.field)
        except TypeError:
            return id(self.field)

    def __repr__(self):
        return f"CheckedColor({self.field!r})"

    def __getattr__(self, name):  # lipschitz and the like: the field's own
        if name == "field":
            raise AttributeError(name)
        return getattr(self.field, name)

    def value(self, x: Any, xp: Any = np) -> Any:
        return check_point_output(f"colour field {type(self.field).__name__}", x, self.field.value(x, xp), "ρ", (3,),
                                  "r, g, b per point", _RHO_FIXES)

    __call__ = value


# -- density models (array API) ---------------------------------------------------------------


def sigmoid(xp: Any, z: Any) -> Any:
    """1/(1 + e^{−z}) without overflow in either branch (so autodiff stays finite)."""
    e = xp.exp(-xp.abs(z))
    return xp.where(z >= 0, 1.0 / (1.0 + e), e / (1.0 + e))


def laplace_cdf(xp: Any, u: Any, beta_inv: float | Any) -> Any:
    """Ψ_β(u): ½ e^{u/β} for u ≤ 0, 1 − ½ e^{−u/β} for u > 0 (one exp of −|u|/β)."""
    e = 0.5 * xp.exp(-xp.abs(u) * beta_inv)
    return xp.where(u <= 0, e, 1.0 - e)


def density(model: str, phi: Any, sharpness: float, xp: Any = np, dphi_dt: Any = None) -> Any:
    """Continuous density σ from field values φ (and ∂φ/∂t = ∇φ·d for ``neus``)."""
    s = _check_model(model, sharpness)
    if model == "nerf":
        return s * sigmoid(xp, -s * phi)
    if model == "volsdf":
        return s * laplace_cdf(xp, -phi, s)
    if model == "neus":
        if dphi_dt is None:
            raise ValueError("neus density needs dphi_dt = ∇φ·d (the derivative of φ along the ray)")
        sig = -s * (1.0 - sigmoid(xp, s * phi)) * dphi_dt
        return xp.where(sig > 0, sig, 0.0 * sig)
    raise ValueError("unisurf has no continuous density: its occupancy is used as alpha directly "
                     "(use occupancy_alpha and composite)")


def occupancy_alpha(phi: Any, sharpness: float, xp: Any = np) -> Any:
    """UNISURF α_i = o(x_i) = sigm(−s φ_i)."""
    s = _check_model("unisurf", sharpness)
    return sigmoid(xp, -s * phi)


def neus_alpha(phi_start: Any, phi_end: Any, sharpness: float, xp: Any = np) -> Any:
    """NeuS discrete α of a section from φ at its two ends: max((Φ_s(φ_a) − Φ_s(φ_b))/Φ_s(φ_a), 0).

    Evaluated as −expm1(log Φ_s(φ_b) − log Φ_s(φ_a)) with log Φ(z) = min(z, 0) − log1p(e^{−|z|}):
    the plain ratio is 0/0 = NaN once Φ_s underflows (sφ < −745 in float64, −104 in float32,
    deep inside the surface), and loses digits to cancellation where both ends are far outside.
    The exponent is clamped at 0 before expm1 rather than α after it: on a section where φ rises
    from deep inside (s·φ from −5,000 to −1,000 at s = 1e4) the exponent is +4,000 and expm1
    overflows, which a clamp after it turns into 0·(−inf) = NaN, and a ``where`` whose untaken
    branch is inf gives NaN gradients under autodiff.
    """
    s = _check_model("neus", sharpness)

    def log_sigmoid(z):
        return xp.minimum(z, xp.zeros_like(z)) - xp.log1p(xp.exp(-xp.abs(z)))

    return -xp.expm1(xp.minimum(log_sigmoid(s * phi_end) - log_sigmoid(s * phi_start), xp.zeros_like(phi_end)))


def alpha_from_density(sigma: Any, delta: Any, xp: Any = np) -> Any:
    """α = 1 − exp(−σ δ) (lecture: 'density → occupancy'), as −expm1 for small σδ accuracy."""
    return -xp.expm1(-sigma * delta)


def composite(alpha: Any, rgb: Any, xp: Any = np) -> tuple[Any, Any]:
    """Alpha compositing along the last sample axis (lecture eqs. 9–10).

    ``alpha`` (..., N), ``rgb`` (..., N, 3) → (C (..., 3), T_N (...)) with weights
    w_i = α_i T_i, T_i = Π_{j<i}(1 − α_j) (an exclusive cumulative product, formed as
    exp of a cumulative sum of log1p(−α)), and T_N the transmittance left after the last sample
    (the background's weight)."""
    logt = xp.cumulative_sum(xp.log1p(-alpha), axis=-1)
    t_incl = xp.exp(logt)
    t_excl = xp.concat([xp.ones_like(alpha[..., :1]), t_incl[..., :-1]], axis=-1)
    w = alpha * t_excl
    return xp.sum(w[..., None] * rgb, axis=-2), t_incl[..., -1]


# -- the continuous reference ------------------------------------------------------------------


def _crossings(scene: Field, o, d, t_min, t_max) -> list[np.ndarray]:
    if scene.info.exact_hits:
        ivs = scene.ray_intervals(o, d)
    else:
        from .numerical import crossings_numeric

        ivs = crossings_numeric(scene, o, d, t_min, t_max)[0]
    return [b[np.isfinite(b) & (b > t_min) & (b < t_max)] for b in ivs]


def _slope_sign_changes(scene: Field, o, d, t_min, t_max, n_samples: int = 2048) -> list[np.ndarray]:
    """Depths where ∂φ/∂t = ∇φ·d changes sign (sampled, then bisected to ~1e-15): the kinks of
    the clipped NeuS density max(−s(1 − Φ_s)∂φ/∂t, 0), made quadrature breakpoints so that
    the adaptive rule does not have to resolve them by subdivision."""
    ts = np.linspace(t_min, t_max, n_samples)
    n = o.shape[0]
    x = (o[:, None, :] + ts[None, :, None] * d[:, None, :]).reshape(-1, 3)
    g = np.einsum("nkj,nj->nk", scene.jet(x)[1].reshape(n, n_samples, 3), d)
    rows, cols = np.nonzero((g[:, 1:] > 0) != (g[:, :-1] > 0))
    lo, hi, glo = ts[cols], ts[cols + 1], g[rows, cols]
    for _ in range(60):
        mid = (lo + hi) / 2
        gm = np.einsum("ij,ij->i", scene.jet(o[rows] + mid[:, None] * d[rows])[1], d[rows])
        same = (gm > 0) == (glo > 0)
        lo, hi = np.where(same, mid, lo), np.where(same, hi, mid)
    out = [[] for _ in range(n)]
    for r, t in zip(rows, (lo + hi) / 2):
        out[r].append(t)
    return out


def render_exact(scene: Field, color, model: str, sharpness: float, o, d, t_min: float, t_max: float,
                 *, return_transmittance: bool = False, tol: float = 1e-12):
    """C = ∫_{t_min}^{t_max} T(t) σ(t) ρ(o + t d) dt per ray, T(t) = exp(−∫_{t_min}^t σ).

    Returns ``(colors (n, 3), error_bound (n,))`` — and ``T(t_max)`` (n,), the weight left for
    the background, when ``return_transmittance``.  Method: adaptive Gauss–Kronrod quadrature
    (``scipy.integrate.quad_vec``, the vector form of ``quad``, here vectorised over rays and
    channels) on segments split at the exact surface crossings and at ±{1, 4, 16}/s around them,
    where σ changes on the scale 1/s (and, for NeuS, where ∂φ/∂t changes sign: the kinks of
    its clipped density); T inside a segment by a nested adaptive quadrature of σ.  Kinks of φ
    itself (CSG seams) are not split at; the adaptive rule resolves them by subdivision, at a
    cost.  Cost: seconds for tens of rays on primitive scenes — a reference, not a renderer.
    ``error_bound`` adds the outer quadrature estimates and the optical-depth errors Δ (inner
    estimates accumulated along the ray) propagated through e^{−τ}: a perturbation |δτ| ≤ Δ
    changes C by at most (e^Δ − 1)·∫e^{−τ}σ|ρ| ≤ (e^Δ − 1)·max|ρ|, with |ρ| ≤ 1 for colour fields
    in [0, 1] such as :class:`SineColor`.  Each quadrature is asked for ``tol`` (default 1e-12),
    so the bound is ≤ 1e-10 unless a quadrature fails (then the bound says so).  The bounds
    are quad's error *estimates* (Gauss–Kronrod differences), not guaranteed enclosures.
    """
    from scipy.integrate import quad_vec

    s = _check_model(model, sharpness)
    if model == "unisurf":
        raise ValueError("unisurf uses occupancy as a discrete alpha (no continuous density); there is "
                         "no continuous integral to compare with — use occupancy_alpha + composite")
    o, d = _points(o, "o"), _points(d, "d")
    if not (math.isfinite(t_min) and math.isfinite(t_max) and t_min < t_max):
        raise ValueError(f"need finite t_min < t_max, got t_min={t_min}, t_max={t_max}")
    n = o.shape[0]
    cross = _crossings(scene, o, d, t_min, t_max)
    try:  # (the first of the NeuS density's reads of ∂φ/∂t, the field's jet: say so before any quadrature)
        kinks = _slope_sign_changes(scene, o, d, t_min, t_max) if model == "neus" else [()] * n
    except NotImplementedError as exc:
        raise ValueError(f"the NeuS density max(−(d/dt)Φ(φ)/Φ(φ), 0) needs ∂φ/∂t (Field.jet), which "
                         f"{type(scene).__name__} does not give: {exc}") from None
    breaks = []
    for c, kk in zip(cross, kinks):
        b = [t_min, t_max, *kk] + [t + k / s * sgn for t in c for k in (0.0, 1.0, 4.0, 16.0) for sgn in (-1.0, 1.0)]
        b = np.unique(np.clip(b, t_min, t_max))
        breaks.append(b)
    K = max(len(b) for b in breaks)
    B = np.stack([np.concatenate([b, np.full(K - len(b), t_max)]) for b in breaks])

    def sigma(t):  # (n,) densities at depths t (n,)
        x = o + t[:, None] * d
        if model == "neus":
            phi, g, _ = scene.jet(x)
            return density(model, phi, s, np, dphi_dt=np.einsum("ij,ij->i", g, d))
        return density(model, scene.value(x), s, np)

    tau = np.zeros(n)
    tau_err = 0.0
    C = np.zeros((n, 3))
    err = np.zeros(n)
    for k in range(K - 1):
        a, L = B[:, k], B[:, k + 1] - B[:, k]
        if not np.any(L > 0):
            continue
        inner_err = [0.0]
        # τ(u) − τ(0) is integrated from the nearest depth already known below u, so each
        # inner quadrature spans a short, usually smooth, piece (not [0, u] again and again);
        # the errors of the chain add up and are tracked per cached depth.
        cache_u, cache_tau, cache_err = [0.0], [np.zeros(n)], [0.0]

        def tau_local(u):
            j = bisect.bisect_right(cache_u, u) - 1
            if cache_u[j] == u:
                return cache_tau[j]
            val, e = quad_vec(lambda v: L * sigma(a + v * L), cache_u[j], u, epsabs=tol, epsrel=0.0, norm="max")
            val = cache_tau[j] + val
            e = cache_err[j] + e
            cache_u.insert(j + 1, u)
            cache_tau.insert(j + 1, val)
            cache_err.insert(j + 1, e)
            inner_err[0] = max(inner_err[0], e)
            return val

        def integrand(u):
            t = a + u * L
            w = L * np.exp(-(tau + tau_local(u))) * sigma(t)
            return (w[:, None] * color.value(o + t[:, None] * d)).ravel()

        val, e = quad_vec(integrand, 0.0, 1.0, epsabs=tol, epsrel=0.0, norm="max")
        C += val.reshape(n, 3)
        seg_tau, e_tau = quad_vec(lambda u: L * sigma(a + u * L), 0.0, 1.0, epsabs=tol, epsrel=0.0, norm="max")
        err += e + np.expm1(tau_err + inner_err[0])
        tau += seg_tau
        tau_err += e_tau
    T_end = np.exp(-tau)
    return (C, err, T_end) if return_transmittance else (C, err)
