"""What the conformance suite's files share: the test scenes with exact answers, the cameras, and
how a check runs a method on a backend (:func:`run`).  The backends come from ``conftest.py``'s
``any_backend`` fixture."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from impls import METHODS, Declined
from reference import Sphere
from reference.rays import pinhole
from reference.scene import Field, SceneInfo, enclosing_ball

# -- test scenes with exact answers -------------------------------------------------------------

SPHERE = Sphere(center=(0.1, -0.2, 0.05), radius=0.8)


@dataclasses.dataclass(frozen=True, eq=False)
class AlgebraicSphere(Field):
    """φ(x) = |x − c|² − r² (lecture's implicit sphere).  |∇φ| = 2|x − c| ≤ 2(R + |c|) on the ball
    |x| ≤ R = 4: that is the Lipschitz bound stated, on that domain (stated, so that root finders
    check it only inside their ray bounds: beyond |x| = 4 it is false, and a step there shows it)."""

    center: tuple = (0.1, -0.2, 0.05)
    radius: float = 0.8
    kind = "algebraic_sphere"

    def own_params(self):
        return {"center": np.array(self.center), "radius": np.array(self.radius)}

    @property
    def info(self):
        return SceneInfo(exact_sdf=False, lipschitz=2 * (4.0 + float(np.linalg.norm(self.center))),
                         distance_bound=False, smooth=True, exact_hits=True, exact_normals=True,
                         exact_curvature=True, exact_hit_param_grad=True, domain="|x| <= 4")

    def bounding_sphere(self):  # the ray bounds keep the search inside the domain of the stated L
        return np.array(self.center), self.radius

    def _eval(self, x, xp, cursor):
        c = cursor.take(self.own_params()["center"])
        r = cursor.take(self.own_params()["radius"])
        v = x - c
        return xp.sum(v * v, axis=-1) - r * r

    def _sphere(self):
        return Sphere(center=self.center, radius=self.radius)

    def first_hit(self, o, d, t_min=0.0):
        return self._sphere().first_hit(o, d, t_min)

    def normal_exact(self, x):
        return self._sphere().normal_exact(x)

    def curvatures_exact(self, x):
        return self._sphere().curvatures_exact(x)

    def laplacian_exact(self, x):
        return np.full(np.shape(x)[:-1], 6.0)

    def hit_param_grad(self, o, d, t):
        return self._sphere().hit_param_grad(o, d, t)


@dataclasses.dataclass(frozen=True, eq=False)
class SphereUnion(Field):
    """min(φ_a, φ_b) of two spheres: a distance bound (L = 1), exact first hit from outside =
    the smaller of the two first hits."""

    a: Sphere = Sphere(center=(-0.4, 0.0, 0.0), radius=0.6)
    b: Sphere = Sphere(center=(0.5, 0.1, 0.0), radius=0.5)
    kind = "union"

    @property
    def children(self):
        return (self.a, self.b)

    @property
    def info(self):
        return SceneInfo(exact_sdf=False, lipschitz=1.0, distance_bound=True, smooth=False, exact_hits=True,
                         exact_normals=False, exact_curvature=False, exact_hit_param_grad=False)

    def _eval(self, x, xp, cursor):
        return xp.minimum(self.a._eval(x, xp, cursor), self.b._eval(x, xp, cursor))

    def first_hit(self, o, d, t_min=0.0):
        return np.minimum(self.a.first_hit(o, d, t_min), self.b.first_hit(o, d, t_min))

    def bounding_sphere(self):
        return enclosing_ball([self.a.bounding_sphere(), self.b.bounding_sphere()])


class LambdaField(Field):
    """A parameter-free field φ(x) = fn(x, xp) with the sphere's stated properties (L = 1): a test
    double for fields that are odd on purpose (NaN everywhere, a thin shell)."""

    kind = "lambda"

    def __init__(self, fn):
        self.fn = fn

    @property
    def info(self):
        return SPHERE.info

    def _eval(self, x, xp, cursor):
        return self.fn(x, xp)


SCENES = {"sphere": SPHERE, "algebraic": AlgebraicSphere(), "union": SphereUnion()}


def camera(n=12):
    """n×n pinhole rays from distance 3; the corners miss every test scene."""
    return pinhole(eye=(0.3, 0.2, 3.0), look_at=(0.0, 0.0, 0.0), fov_deg=45.0, width=n, height=n)


def xfail_if_expected(request, backend, check: str):
    """Mark the test xfail(strict) when ``backend`` lists ``check`` among its expected failures."""
    reason = backend.capabilities.expected_failure(check)
    if reason:
        request.applymarker(pytest.mark.xfail(strict=True, reason=f"{backend.id}: {reason}"))


def skip_unless_offered(backend, method, dtype="float64"):
    """Skip (with the reason) where ``backend`` does not offer ``method`` (``backend.methods()``:
    ``MethodSpec.libs`` leaves e.g. scipy's refiner to numpy, and a plug-in may offer a subset of the
    catalog; that it declines such a method cleanly is checked in tests/test_chandrupatla.py) or
    ``dtype`` (``capabilities.dtypes``)."""
    if method not in backend.methods():
        pytest.skip(f"{backend.id} does not offer {method} (MethodSpec.libs = {METHODS[method].libs}; "
                    f"not in its methods())")
    if dtype not in backend.capabilities.dtypes:
        pytest.skip(f"{backend.id} does not support {dtype} (capabilities.dtypes: {backend.capabilities.dtypes})")


def run(backend, method, scene, o, d, *, t_min=0.0, t_max=10.0, t_hit=None, **knobs):
    """``method`` on the rays, float64, as a RayResult; a skip where the backend does not offer the
    method or declines the scene (:class:`impls.protocol.Declined`: e.g. a compiling backend and
    one of this module's test fields, which it cannot compile)."""
    skip_unless_offered(backend, method)
    try:
        prep = backend.prepare(method, scene, o, d, dtype="float64", t_min=t_min, t_max=t_max, t_hit=t_hit, **knobs)
    except Declined as exc:
        pytest.skip(f"{backend.id} declines {method} on {type(scene).__name__}: {exc}")
    out = prep.run()
    backend.synchronize(out)
    return prep.result(out)


# -- root finders ---------------------------------------------------------------------------------

ROOT_METHODS = [m for m, s in METHODS.items() if s.family == "root"]
TIGHT = {"sphere_trace": dict(tol=1e-13, max_steps=20000), "hybrid_secant": dict(xtol=1e-13),
         "march_bisect": dict(xtol=1e-13, step=0.01), "march_secant": dict(xtol=1e-13, step=0.01),
         "march_newton": dict(xtol=1e-13, step=0.01), "march_chandrupatla": dict(xtol=1e-13, step=0.01),
         "hybrid_chandrupatla": dict(xtol=1e-13), "raycast": {}}


def applicable(method, scene) -> bool:
    return METHODS[method].skip_reason(scene) is None


def sphere_trace_allowance(scene, o, exact, knobs, dtype="float64", method="sphere_trace"):
    """Per ray, a certified method's allowance δ at depth ``exact`` (docs/methods.md): for
    ``sphere_trace`` δ = max(tol/L, 4·rounding, 2ε|t|), for the hybrids (``hybrid_*``, their closing
    width) δ = max(xtol, 4·gain·rounding, 2ε|t|), rounding = 8ε(|t| + |o|₁ + the scene's extent
    and offset), the model of :func:`impls.core.rootfind.resolution` (0 where φ is not a distance
    bound), gain the scene's rounding gain: a CONVERGED depth lies within it of the first crossing
    (the hybrids' to within ``min_step`` more)."""
    from impls.core.methods_root import resolves, rounding_gain, rounding_scale

    eps = float(np.finfo(dtype).eps)
    defaults = {k.name: k.default for k in METHODS[method].knobs}
    t = np.abs(np.where(np.isfinite(exact), exact, 0.0))
    rounding = 8.0 * eps * (t + np.abs(o).sum(axis=1) + rounding_scale(scene)) if resolves(scene) else 0.0 * t
    if method == "sphere_trace":
        tol = knobs.get("tol", defaults["tol"]) / float(scene.info.lipschitz)
    else:
        tol, rounding = knobs.get("xtol", defaults["xtol"]), rounding_gain(scene) * rounding
    return np.maximum(np.maximum(tol, 4.0 * rounding), 2.0 * eps * t)


def depth_resolved(method, scene, o, d, exact, knobs, dtype="float64", margin=0.75):
    """The hits a certified method must answer CONVERGED at ``knobs``: for ``sphere_trace`` and
    the hybrids, those whose depth the dtype resolves to their allowance δ
    (:func:`sphere_trace_allowance`).  Along a ray meeting the surface at slope s = |∇φ·d|/L, φ's
    sign is rounding (:func:`impls.core.rootfind.resolution`, the rounding model the finder
    certifies with) over a stretch 2·rounding/s long, so no bracket of resolved signs is
    narrower: a hit where that stretch exceeds ``margin``·δ may be UNCERTIFIED instead.  The same
    for the constant-step marches where they verify their brackets (a bound to check, φ a distance
    bound: :attr:`impls.core.rootfind.MarchRefine.verifies`).  For the other methods, every hit."""
    hit = np.isfinite(exact)
    from impls.core.methods_root import resolves, rounding_gain, rounding_scale, step_field

    scene = step_field(scene)  # (what the certified methods march on: impls.base)
    if not (method == "sphere_trace" or method.startswith(("hybrid_", "march_"))) or not resolves(scene):
        return hit  # (rounding not modelled: only φ = 0 is unresolved)
    if method.startswith("march_") and not scene.info.lipschitz:
        return hit  # (a march without a bound to check verifies nothing: MarchRefine.verifies)
    lip = float(scene.info.lipschitz)
    t = np.where(hit, exact, 0.0)
    rounding = 8.0 * float(np.finfo(dtype).eps) * (np.abs(t) + np.abs(o).sum(axis=1) + rounding_scale(scene))
    delta = sphere_trace_allowance(scene, o, exact, knobs, dtype, method)
    h = 1e-6  # (a central difference of φ along the ray: any scene, error O(h²) on a smooth surface)
    slope = np.abs(scene.value(o + (t + h)[:, None] * d) - scene.value(o + (t - h)[:, None] * d)) / (2.0 * h * lip)
    with np.errstate(divide="ignore"):
        return hit & (2.0 * rounding_gain(scene) * rounding / slope <= margin * delta)


def hits(scene, n=8):
    o, d = camera(n)
    t = scene.first_hit(o, d, 0.0)
    hit = np.isfinite(t)
    x = o + np.where(hit, t, 0.0)[:, None] * d
    return o, d, t, hit, x


def tol_for(backend, autodiff_tol, fd_tol):
    """Autodiff backends are held to rounding level; finite-difference ones to their stated error."""
    return autodiff_tol if backend.capabilities.autodiff else fd_tol



def plant_bad_rays(o, d):
    """Copies of 9 rays ``o``, ``d`` with a NaN origin (ray 1), an infinite origin (4), a zero
    direction (6) and a NaN direction (7): ``(o, d, flagged)``, the rays every method must
    answer BAD_INPUT."""
    o, d = o.copy(), d.copy()
    o[1, 0] = np.nan
    o[4, 2] = np.inf
    d[6] = 0.0
    d[7, 1] = np.nan
    flagged = np.zeros(len(o), bool)
    flagged[[1, 4, 6, 7]] = True
    return o, d, flagged
