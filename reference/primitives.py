"""Primitive shapes with exact SDFs and exact answers.

Each primitive's ``_eval`` is the textbook SDF (I. Quilez, "distance functions",
https://iquilezles.org/articles/distfunctions/; J. C. Hart, "Sphere tracing", The Visual
Computer 12, 1996).  Exact ray intervals, normals and curvatures are float64 numpy.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from .quadric import ray_sphere_roots
from .scene import Field, SceneInfo, norm


def _vec3(name: str, v) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be 3 finite numbers, got {v!r}")
    return a


def _positive(name: str, v) -> float:
    v = float(v)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be a finite number > 0, got {v!r}")
    return v


@dataclasses.dataclass(frozen=True, eq=False)
class Sphere(Field):
    """Sphere of centre c and radius r: φ(x) = |x − c| − r (exact SDF, L = 1).

    Exact answers: first hit by the stable quadratic (:func:`ray_sphere_roots`); normal
    n = (x − c)/|x − c|; principal curvatures κ1 = κ2 = 1/r, so the mean curvature
    H = (κ1 + κ2)/2 = 1/r and the lecture's sum κ1 + κ2 = Δφ = 2/r on the surface.
    Hit-depth derivatives (ray o + t d, |d| = 1, hit x = o + t d, n = (x − c)/r):
    from φ(o + t d; c, r) = 0, dt/dr = 1/(n·d) and dt/dc = n/(n·d).
    """

    center: tuple = (0.0, 0.0, 0.0)
    radius: float = 1.0
    kind = "sphere"

    def __post_init__(self):
        object.__setattr__(self, "center", tuple(_vec3("center", self.center).tolist()))
        object.__setattr__(self, "radius", _positive("radius", self.radius))

    def own_params(self):
        return {"center": np.array(self.center), "radius": np.array(self.radius)}

    @property
    def info(self) -> SceneInfo:
        return SceneInfo(
            exact_sdf=True, lipschitz=1.0, distance_bound=True, smooth=True, exact_hits=True,
            exact_normals=True, exact_curvature=True, exact_hit_param_grad=True,
        )

    def _eval(self, x, xp, cursor):
        c = cursor.take(self.own_params()["center"])
        r = cursor.take(self.own_params()["radius"])
        return norm(xp, x - c) - r

    # exact answers -------------------------------------------------------------------------
    def ray_intervals(self, o, d):
        t0, t1 = ray_sphere_roots(o, d, self.center, self.radius)
        return [np.array([a, b]) if np.isfinite(a) and a < b else np.zeros(0) for a, b in zip(t0, t1)]

    def first_hit(self, o, d, t_min: float = 0.0):
        t0, t1 = ray_sphere_roots(o, d, self.center, self.radius)
        t = np.where(t0 > t_min, t0, np.where(t1 > t_min, t1, np.inf))
        return np.where(np.isnan(t), np.inf, t)

    def normal_exact(self, x):
        v = np.asarray(x, np.float64) - np.asarray(self.center)
        return v / np.linalg.norm(v, axis=-1, keepdims=True)

    def curvatures_exact(self, x):
        k = np.full(np.shape(x)[:-1], 1.0 / self.radius)
        return k, k.copy()

    def hit_param_grad(self, o, d, t):
        """dt/dθ per ray, θ = (c_x, c_y, c_z, r) in ``param_vector`` order; shape (n, 4)."""
        x = np.asarray(o) + np.asarray(t)[:, None] * np.asarray(d)
        n = self.normal_exact(x)
        nd = np.einsum("ij,ij->i", n, d)
        return np.concatenate([n / nd[:, None], (1.0 / nd)[:, None]], axis=1)
