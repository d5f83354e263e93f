"""Build the root-finder state machine of a ``root``-family method from its knobs."""

from __future__ import annotations

import math

import numpy as np

from .rootfind import MarchRefine, SphereTrace


def lipschitz_step(scene) -> float:
    lip = scene.info.lipschitz
    if not lip:
        raise ValueError(f"{type(scene).__name__} states no Lipschitz bound; sphere tracing needs one")
    return 1.0 / float(lip)


def search_bounds(scene, knobs: dict, theta=None):
    """The scene whose ray bounds (:meth:`reference.scene.Field.ray_bounds`) the root finders
    clip rays to when knob ``bounds`` is on and φ is evaluated at the stored parameters (a θ
    passed in may move the surface out of the stored parameters' bounds), else None."""
    if not knobs.get("bounds", 1) or theta is not None:
        return None
    return scene


def rounding_scale(scene) -> float:
    """|centre| + radius of the scene's bounding ball (0 without one): the magnitude of φ's
    intermediates beyond the point itself, for the rounding slack of the Lipschitz check
    (:func:`impls.core.rootfind.lipschitz_violated`)."""
    ball = scene.bounding_sphere()
    if ball is None:
        return 0.0
    v = float(np.sqrt(np.sum(np.square(np.asarray(ball[0], np.float64))))) + float(ball[1])
    return v if math.isfinite(v) else 0.0


def marching_check(scene, bounds, theta) -> float | None:
    """1/L for constant-step marching to check on its steps, or None: the scene declares a bound
    L, φ is evaluated at the stored parameters (the bound is theirs) and, for a bound stated on
    a domain only, the search is clipped to the ray bounds (marching does not rely on L, so it
    checks it only where the scene claims it)."""
    lip = scene.info.lipschitz
    if not lip or theta is not None or (getattr(scene.info, "domain", None) is not None and bounds is None):
        return None
    return 1.0 / float(lip)


LADDER = 16  # ladder samples when the knob is -1 ("the driver's choice") and the driver states none


def make_root_finder(method: str, scene, t_min: float, t_max: float, knobs: dict, theta=None, ladder: int = LADDER):
    """The algorithm object (``init``/``step``) of root method ``method`` with validated knobs
    (a knob left out takes its default: callers inside isobench may pass only some); ``ladder``
    is the loop driver's choice of ladder samples where the knob leaves it to the driver (-1)."""
    from ..methods import METHODS

    knobs = {**{k.name: k.default for k in METHODS[method].knobs}, **knobs}
    bounds = search_bounds(scene, knobs, theta)
    # a bound stated on a domain only (the algebraic sphere's on |x| ≤ R) is not checked past the ray bounds
    probe = getattr(scene.info, "domain", None) is None
    scale = rounding_scale(scene)
    if knobs.get("ladder", -1) == -1:
        knobs["ladder"] = ladder
    if method == "sphere_trace":
        return SphereTrace(inv_lip=lipschitz_step(scene), tol=knobs["tol"], max_steps=knobs["max_steps"],
                           omega=knobs["omega"], t_min=t_min, t_max=t_max, bounds=bounds, probe=probe,
                           scale=scale)
    if method in ("hybrid_secant", "render_surface"):
        return MarchRefine(refine="secant", min_step=knobs["min_step"], inv_lip=lipschitz_step(scene), xtol=knobs["xtol"],
                           max_steps=knobs["max_steps"], t_min=t_min, t_max=t_max,
                           overstep=max(knobs["overstep"], knobs["min_step"]), bounds=bounds, ladder=knobs["ladder"],
                           ladder_after=knobs["ladder_after"], extrapolate=knobs["extrapolate"],
                           reach=knobs["reach"], probe=probe, scale=scale)
    if method.startswith("march_"):
        return MarchRefine(refine=method[len("march_"):], min_step=knobs["step"], inv_lip=None, xtol=knobs["xtol"],
                           max_steps=knobs["max_steps"], t_min=t_min, t_max=t_max, bounds=bounds, ladder=knobs["ladder"],
                           ladder_after=knobs["ladder_after"], extrapolate=0.0, scale=scale,
                           check_inv_lip=marching_check(scene, bounds, theta))
    raise ValueError(f"{method!r} is not a root finder")


ROOT_METHODS = ("sphere_trace", "hybrid_secant", "march_bisect", "march_secant", "march_newton")


def root_impls(solve, lib: str) -> dict:
    """``{method: impl}`` for every root method, each a thin call of the backend's ``solve``."""

    def bind(method):
        def impl(backend, scene, o, d, *, t_min, t_max, t_hit, **knobs):
            return solve(method, backend, scene, o, d, t_min=t_min, t_max=t_max, **knobs)

        impl.__name__ = method
        impl.__doc__ = f"{method} on {lib} (see impls.core.rootfind and impls.methods.METHODS[{method!r}])."
        return impl

    return {m: bind(m) for m in ROOT_METHODS}
