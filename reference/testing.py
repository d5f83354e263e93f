"""Test helpers (for isobench's tests and for plug-in authors): one scene of every node type, and an mpmath
"array namespace" so the very same ``_eval`` formulas run at 40+ digits."""

from __future__ import annotations

import mpmath
import numpy as np

from .csg import Complement, Difference, Intersection, Union
from .mlp import MLPField
from .implicits import AlgebraicSphere, Ellipsoid, Scaled
from .primitives import Box, CappedCylinder, Capsule, Plane, Sphere, Torus
from .transform import Transform


def every_node() -> dict:
    """One small scene per node type (placed off the origin so no symmetry hides a bug)."""
    rv, tr = (0.3, -0.5, 0.2), (0.05, -0.02, 0.1)
    return {
        "sphere": Sphere((0.1, -0.2, 0.05), 0.8),
        "plane": Plane((0.2, 0.3, 1.0), 0.1),
        "box": Transform.from_rotvec(Box((0.6, 0.4, 0.3)), rv, tr),
        "torus": Transform.from_rotvec(Torus(1.0, 0.3), rv, tr),
        "capsule": Capsule((-0.5, -0.3, 0.1), (0.4, 0.5, -0.2), 0.35),
        "cylinder": Transform.from_rotvec(CappedCylinder(0.5, 0.7), rv, tr),
        "algsphere": AlgebraicSphere((0.1, 0.0, -0.1), 0.9),
        "ellipsoid": Transform.from_rotvec(Ellipsoid((1.0, 0.6, 0.4)), rv),
        "scaled": Scaled(Torus(1.0, 0.25), 3.0),
        "union": Union(Torus(1.0, 0.25), Box((0.4, 0.4, 0.4))),
        "intersection": Intersection(Sphere(radius=1.0), Transform.from_rotvec(Box((0.8, 0.8, 0.8)), (0.4, 0.4, 0.0))),
        "difference": Difference(Box((0.7, 0.7, 0.7)), Sphere(radius=0.9)),
        "complement": Complement(Sphere(radius=1.0)),
        "mlp": MLPField(),
    }


class MPNamespace:
    """numpy with object arrays of mpmath numbers: the array-API calls a scene makes, at
    ``mpmath.mp.dps`` digits.  Only functions whose numpy version would not dispatch to mpf
    are replaced."""

    _vec = {name: np.vectorize(getattr(mpmath, name), otypes=[object])
            for name in ("sqrt", "exp", "log", "tanh", "log1p", "expm1", "sin", "cos", "tan", "atan")}

    def __getattr__(self, name):
        if name in self._vec:
            return self._vec[name]
        return getattr(np, name)

    def asarray(self, v, dtype=None, device=None):
        return np.asarray(v, dtype=object)


MP = MPNamespace()


def to_mp(x: np.ndarray) -> np.ndarray:
    return np.vectorize(mpmath.mpf, otypes=[object])(np.asarray(x, np.float64))


def mp_value(scene, x_mp: np.ndarray) -> np.ndarray:
    """φ at mpmath object-array points (constants promoted to mpf by the object arithmetic)."""
    return scene.value(x_mp, MP)
