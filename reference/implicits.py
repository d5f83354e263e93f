"""Implicit functions that are *not* signed distances, with their true Lipschitz constant.

For these φ the zero set is a known surface but |∇φ| ≠ 1, so sphere tracing needs the step
φ/L with L = sup |∇φ| over a stated domain (mean-value theorem: the lecture's Proposition 2).
The domain is part of the scene (``domain_radius``): outside it the bound does not hold, and
cases built on these scenes keep their rays inside it.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .curvature import principal_from_hessian
from .primitives import _positive, _vec3
from .quadric import ray_sphere_roots
from . import intervals as iv
from . import raybounds
from .arrays import sum_last
from .scene import Field, SceneInfo, _points


def _info(lipschitz, domain, **kw):
    base = dict(exact_sdf=False, lipschitz=lipschitz, distance_bound=False, smooth=True, exact_hits=True,
                exact_normals=True, exact_curvature=True, exact_hit_param_grad=True, domain=domain)
    base.update(kw)
    return SceneInfo(**base)


@dataclasses.dataclass(frozen=True, eq=False)
class AlgebraicSphere(Field):
    """The lecture's algebraic sphere φ(x) = |x − c|² − r² (θ = (c, r)).

    Zero set: the sphere of radius r.  ∇φ = 2(x − c), so on the ball |x − c| ≤ D the exact
    Lipschitz constant is L = 2D (attained on the boundary).  Hessian 2I ⇒ κ1 = κ2 = 1/r, but
    Δφ = 6 everywhere: the Laplacian is *not* the curvature sum for a non-SDF.
    ∂φ/∂c = −2(x − c), ∂φ/∂r = −2r.
    """

    center: tuple = (0.0, 0.0, 0.0)
    radius: float = 1.0
    domain_radius: float = 4.0
    kind = "algsphere"

    def __post_init__(self):
        object.__setattr__(self, "center", tuple(_vec3("center", self.center).tolist()))
        object.__setattr__(self, "radius", _positive("radius", self.radius))
        object.__setattr__(self, "domain_radius", _positive("domain_radius", self.domain_radius))
        if not self.radius < self.domain_radius:
            # the bound 2D holds on |x − c| ≤ D only: a surface reaching past it is not bounded there
            raise ValueError(f"domain_radius must exceed radius (the bound 2·domain_radius holds on |x − c| ≤ "
                             f"domain_radius, which must hold the surface), got radius={self.radius:g}, "
                             f"domain_radius={self.domain_radius:g}: pass a larger domain_radius")

    def own_params(self):
        return {"center": np.array(self.center), "radius": np.array(self.radius)}

    @property
    def info(self):
        return _info(2.0 * self.domain_radius, f"|x - c| <= {self.domain_radius:g}")

    def bounding_sphere(self):
        return np.array(self.center), self.radius

    def domain_hulls(self):
        """(the sphere itself, the domain ball |x − c| ≤ D) as exact SDFs (r < D, checked on construction)."""
        from .primitives import Sphere

        return Sphere(center=self.center, radius=self.radius), Sphere(center=self.center, radius=self.domain_radius)

    def _eval(self, x, xp, cursor):
        c = cursor.take(self.own_params()["center"])
        r = cursor.take(self.own_params()["radius"])
        v = x - c
        return sum_last(xp, v * v) - r * r

    def ray_interval_batch(self, o, d):
        return iv.batch_from_bounds(*ray_sphere_roots(o, d, self.center, self.radius))

    def _jet(self, x):
        v = x - np.asarray(self.center)
        dth = np.concatenate([-2 * v, np.full((x.shape[0], 1), -2 * self.radius)], axis=1)
        return np.einsum("ij,ij->i", v, v) - self.radius**2, 2 * v, dth

    def curvatures_exact(self, x):
        x = _points(x)
        return principal_from_hessian(2 * (x - np.asarray(self.center)), np.broadcast_to(2 * np.eye(3), (x.shape[0], 3, 3)))


@dataclasses.dataclass(frozen=True, eq=False)
class Ellipsoid(Field):
    """Axis-aligned ellipsoid quadric φ(x) = Σᵢ xᵢ²/aᵢ² − 1 centred at the origin (θ = (a₁, a₂, a₃)).

    ∇φ = 2xᵢ/aᵢ²; on the ball |x| ≤ D, L = sup|∇φ| = 2D/min(aᵢ)² (attained on the shortest
    axis).  Hits: the unit sphere in the scaled coordinates x/a (stable quadratic with
    non-unit direction).  Hessian diag(2/aᵢ²) ⇒ curvatures by :func:`principal_from_hessian`.
    ∂φ/∂aᵢ = −2xᵢ²/aᵢ³.  Place it with :class:`reference.transform.Transform`.
    """

    axes: tuple = (1.0, 0.75, 0.5)
    domain_radius: float = 4.0
    kind = "ellipsoid"

    def __post_init__(self):
        a = _vec3("axes", self.axes)
        if not np.all(a > 0):
            raise ValueError(f"axes must be 3 numbers > 0, got {self.axes!r}")
        object.__setattr__(self, "axes", tuple(a.tolist()))
        object.__setattr__(self, "domain_radius", _positive("domain_radius", self.domain_radius))
        if not max(self.axes) < self.domain_radius:
            # the bound 2D/a_min² holds on |x| ≤ D only: a surface reaching past it is not bounded there
            raise ValueError(f"domain_radius must exceed the longest axis (the bound holds on |x| ≤ domain_radius, "
                             f"which must hold the surface), got axes={self.axes!r}, "
                             f"domain_radius={self.domain_radius:g}: pass a larger domain_radius")

    def own_params(self):
        return {"axes": np.array(self.axes)}

    @property
    def info(self):
        return _info(2.0 * self.domain_radius / min(self.axes) ** 2, f"|x| <= {self.domain_radius:g}")

    def bounding_sphere(self):
        return np.zeros(3), max(self.axes)

    def domain_hulls(self):
        """(the ball of radius maxᵢ aᵢ, the domain ball |x| ≤ D) as exact SDFs (maxᵢ aᵢ < D, checked on
        construction)."""
        from .primitives import Sphere

        return Sphere(radius=max(self.axes)), Sphere(radius=self.domain_radius)

    def ray_bounds(self, xp, o, d):
        """The chord of its bounding box |xᵢ| ≤ aᵢ, met with that of the ball |x| ≤
        :meth:`search_radius` where the box's corners reach past the domain: L holds on the domain
        only, and a step from a corner outside it could cross a grazing chord of the surface
        (axes (3, 3, 3) in |x| ≤ 3.3, seen from (10, 10, 10): 1,596 of 16,384 rays
        LIPSCHITZ_VIOLATED on the box alone)."""
        box = raybounds.box_chord(xp, o, d, self.axes, max(self.axes))
        r = self.search_radius()
        return box if r is None else raybounds.meet(xp, box, raybounds.ball_chord(xp, o, d, np.zeros(3), r))

    def search_radius(self) -> float | None:
        """(1 − 10⁻⁵)·D where the bounding box's corners (|a|, padded) reach past the domain
        |x| ≤ D and the surface (within |x| ≤ maxᵢ aᵢ) lies inside that ball; else None (the box
        alone).  The margin keeps the ball's padded chord (10⁻⁶ of its radius, plus rounding)
        inside the domain."""
        radius = (1.0 - 1e-5) * self.domain_radius
        if float(np.linalg.norm(self.axes)) * (1.0 + 1e-5) < self.domain_radius or not max(self.axes) < radius:
            return None
        return radius

    def _eval(self, x, xp, cursor):
        a = cursor.take(self.own_params()["axes"])
        y = x / a
        return sum_last(xp, y * y) - 1.0

    def ray_interval_batch(self, o, d):
        a = np.asarray(self.axes)
        return iv.batch_from_bounds(*ray_sphere_roots(_points(o, "o") / a, _points(d, "d") / a, np.zeros(3), 1.0))

    def _jet(self, x):
        a = np.asarray(self.axes)
        return np.sum((x / a) ** 2, axis=1) - 1.0, 2 * x / a**2, -2 * x**2 / a**3

    def curvatures_exact(self, x):
        x = _points(x)
        a = np.asarray(self.axes)
        return principal_from_hessian(2 * x / a**2, np.broadcast_to(np.diag(2 / a**2), (x.shape[0], 3, 3)))


@dataclasses.dataclass(frozen=True, eq=False)
class Scaled(Field):
    """k·φ for a child φ and k > 0 (θ = (k, θ_child)): the same surface, not an SDF unless
    k = 1.  Lipschitz k·L_child; a distance bound when k ≤ 1 and the child is one.
    ∂(kφ)/∂k = φ (= 0 on the surface, so dt/dk = 0)."""

    child: Field = None
    scale: float = 2.0
    kind = "scaled"

    def __post_init__(self):
        if not isinstance(self.child, Field):
            raise ValueError(f"child must be a Field (a scene node), got {type(self.child).__name__}")
        object.__setattr__(self, "scale", _positive("scale", self.scale))

    @property
    def children(self):
        return (self.child,)

    def own_params(self):
        return {"scale": np.array(self.scale)}

    @property
    def info(self):
        ci = self.child.info
        return dataclasses.replace(
            ci, exact_sdf=ci.exact_sdf and self.scale == 1.0,
            lipschitz=None if ci.lipschitz is None else self.scale * ci.lipschitz,
            distance_bound=ci.distance_bound and self.scale <= 1.0)

    def bounding_sphere(self):
        return self.child.bounding_sphere()  # k > 0: the same solid

    def ray_bounds(self, xp, o, d):
        return self.child.ray_bounds(xp, o, d)

    def _eval(self, x, xp, cursor):
        k = cursor.take(self.own_params()["scale"])
        return k * self.child._eval(x, xp, cursor)

    def ray_intervals(self, o, d):
        return self.child.ray_intervals(o, d)

    def ray_interval_batch(self, o, d):
        return self.child.ray_interval_batch(o, d)

    def first_hit(self, o, d, t_min: float = 0.0):
        return self.child.first_hit(o, d, t_min)

    def _jet(self, x):
        phi, g, dth = self.child._jet(x)
        return self.scale * phi, self.scale * g, np.concatenate([phi[:, None], self.scale * dth], axis=1)

    def curvatures_exact(self, x):
        return self.child.curvatures_exact(x)
