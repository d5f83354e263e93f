"""The one place where the claims obtain pieces owned by ``reference/`` and ``impls/``.

Shapes, CSG nodes, the colour field, the density models and the MLP field are the project's own
reference objects (:mod:`reference`); what is left here is the thin glue the claims need on top of
them (a display label, the curvature sum, the claims' names for the density models).  The
backends' root finders are reached through the registry by :func:`prepare_trace`.

All functions take and return float64 numpy arrays; points have shape ``(..., 3)``.
"""

from __future__ import annotations

import numpy as np

from reference import Field, MLPField
from reference import rendering as _rendering
from reference.rendering import SineColor

Array = np.ndarray


# -- shapes ---------------------------------------------------------------------------------------


def label(scene: Field) -> str:
    """A short human label of a reference scene for trial conditions and key numbers."""
    k = scene.kind
    if k == "sphere":
        return f"sphere SDF |x−c|−{scene.radius:g}"
    if k == "algsphere":
        return f"algebraic sphere |x|²−{scene.radius**2:g}"
    if k == "torus":
        return f"torus SDF R={scene.major:g} r={scene.minor:g}"
    if k == "box":
        return f"box SDF half={tuple(scene.half_size)}"
    if k == "ellipsoid":
        return f"ellipsoid quadric axes={tuple(scene.axes)}"
    if k == "scaled":
        return f"{scene.scale:g}·({label(scene.child)})"
    if k in ("union", "intersection", "difference"):
        return f"{k}({', '.join(label(c) for c in scene.children)})"
    if k == "complement":
        return f"complement({label(scene.child)})"
    return k


def curvature_sum(scene: Field, x: Array) -> Array:
    """Exact κ1 + κ2 (reference convention: a sphere's is +2/r) at surface points ``x`` (..., 3)."""
    x = np.asarray(x, float)
    k1, k2 = scene.curvatures_exact(x.reshape(-1, 3))
    return (k1 + k2).reshape(x.shape[:-1])


# -- colour field -------------------------------------------------------------------------------


def colour_field(gamma: float) -> SineColor:
    """The reference RGB colour field :class:`reference.rendering.SineColor` with its frequency set so
    that its exact Lipschitz constant ½ω‖A‖₂ (‖·‖₂ of the RGB vector) equals ``gamma``."""
    base = SineColor()
    return SineColor(frequency=base.frequency * gamma / base.lipschitz)


# -- density models along a ray -------------------------------------------------------------------

#: the reference's density models (:data:`reference.rendering.MODELS`), in report order
DENSITY_MODELS = ("unisurf", "nerf", "volsdf", "neus")
#: the models with a continuous density, hence a continuous integral (:func:`render_exact`)
CONTINUOUS_MODELS = ("nerf", "volsdf", "neus")


def density_alphas(model: str, phi_mid: Array, phi_lo: Array, phi_hi: Array, delta: Array, s: float) -> Array:
    """Discrete opacities α_i of samples for a reference density model of sharpness s.

    phi_mid: φ at the sample points; phi_lo/phi_hi: φ at the section ends; δ_i: section lengths.
    ``unisurf``: α = sigm(−sφ) (``occupancy_alpha``); ``nerf``/``volsdf``: α = 1 − exp(−σδ) with the
    reference ``density``; ``neus``: ``neus_alpha`` from the section ends.  Formulas and sources:
    :mod:`reference.rendering`.
    """
    R = _rendering
    if model == "unisurf":
        return R.occupancy_alpha(phi_mid, s)
    if model == "neus":
        return R.neus_alpha(phi_lo, phi_hi, s)  # log-space in the reference: finite deep inside too
    return R.alpha_from_density(R.density(model, phi_mid, s), delta)


# -- MLP field ----------------------------------------------------------------------------------


def mlp_field() -> MLPField:
    """The stored-weight reference MLP (``reference/data/mlp_blob.npz``); its exact spectral-norm bound
    is ``.lipschitz_bound``."""
    return MLPField()


# -- root finding through a backend ---------------------------------------------------------------


def backend(backend_id: str = "numpy"):
    """A registered backend (:func:`impls.registry.resolve`); RuntimeError with the reason if unavailable."""
    from impls import registry

    b = registry.resolve(backend_id)
    if isinstance(b, registry.Unavailable):
        raise RuntimeError(f"backend {backend_id} unavailable: {b.reason}")
    return b


def prepare_trace(scene, o: Array, d: Array, *, method: str = "sphere_trace", t_max: float = 10.0,
                  backend_id: str = "numpy", **knobs):
    """A backend's root finder ``method`` (any ``root``-family method of :data:`impls.METHODS`:
    ``sphere_trace``, ``hybrid_secant``, ``march_bisect``/``march_secant``/``march_newton``) prepared
    on these rays from t = 0, with its knobs (validated by the method's spec; unspecified knobs take
    the spec's defaults).  Returns (run, to_numpy): ``run()`` does the timed work (device
    synchronised) and ``to_numpy(out)`` gives (t, status, evals) as float64/int numpy."""
    from impls import METHODS

    if method not in METHODS or METHODS[method].family != "root":
        roots = sorted(m for m, s in METHODS.items() if s.family == "root")
        raise ValueError(f"method must be a root finder, one of {roots}; got {method!r}")
    b = backend(backend_id)
    prep = b.prepare(method, scene, o, d, t_min=0.0, t_max=t_max, **knobs)

    def run():
        out = prep.run()
        b.synchronize(out)
        return out

    def to_numpy(out):
        res = prep.result(out)
        return res.t, res.status, res.evals

    return run, to_numpy
