"""Build the root-finder state machine of a ``root``-family method from its knobs."""

from __future__ import annotations

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
    if knobs.get("ladder", -1) == -1:
        knobs["ladder"] = ladder
    if method == "sphere_trace":
        return SphereTrace(inv_lip=lipschitz_step(scene), tol=knobs["tol"], max_steps=knobs["max_steps"],
                           omega=knobs["omega"], t_min=t_min, t_max=t_max, bounds=bounds, probe=probe)
    if method in ("hybrid_secant", "render_surface"):
        return MarchRefine(refine="secant", min_step=knobs["min_step"], inv_lip=lipschitz_step(scene), xtol=knobs["xtol"],
                           max_steps=knobs["max_steps"], t_min=t_min, t_max=t_max,
                           overstep=max(knobs["overstep"], knobs["min_step"]), bounds=bounds, ladder=knobs["ladder"],
                           ladder_after=knobs["ladder_after"], extrapolate=knobs["extrapolate"],
                           reach=knobs["reach"], probe=probe)
    if method.startswith("march_"):
        return MarchRefine(refine=method[len("march_"):], min_step=knobs["step"], inv_lip=None, xtol=knobs["xtol"],
                           max_steps=knobs["max_steps"], t_min=t_min, t_max=t_max, bounds=bounds, ladder=knobs["ladder"],
                           ladder_after=knobs["ladder_after"], extrapolate=0.0)
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
