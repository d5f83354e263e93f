"""Rigid placement of a scene: φ(x) = φ_child(Rᵀ(x − τ)).

R is a rotation (orthonormal, det +1) stored as given and never inverted numerically: the
inverse map is Rᵀ(x − τ) applied directly (x' = (x − τ) R in row-vector form), so an exact SDF
stays an exact SDF (distances are preserved), and depths along a ray are unchanged (rays map to
o' = (o − τ)R, d' = d R).  θ = (τ, θ_child); R is fixed.
Gradients rotate back: ∇φ(x) = R ∇φ_child(x'); ∂φ/∂τ = −∇φ(x).  Curvatures are invariant.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .arrays import const
from .scene import Field, _points

#: max |RᵀR − I| accepted for a rotation: 32 ε
ROTATION_TOLERANCE = 32 * float(np.finfo(np.float64).eps)


class Transform(Field):
    kind = "transform"

    def __init__(self, child: Field, rotation=None, translation=(0.0, 0.0, 0.0)):
        if not isinstance(child, Field):
            raise ValueError(f"child must be a Field (a scene node), got {type(child).__name__}")
        R = np.eye(3) if rotation is None else np.asarray(rotation, np.float64)
        if R.shape != (3, 3) or not np.all(np.isfinite(R)):
            raise ValueError(f"rotation must be a finite 3×3 matrix, got shape {R.shape}")
        # to float64's rounding: a rotation δ off orthonormal stretches distances by up to √(1 + 3δ),
        # and the certified steps φ/L and the child's ray bounds (unit directions) would be off by
        # that, which no rounding model covers past a few ε (1e-12 was accepted: a step φ/L from
        # 1e6 away could end 1.5e-6 past the surface).  scipy's matrices are within 6ε (20,000
        # random rotations).
        off = float(np.max(np.abs(R.T @ R - np.eye(3))))
        if off > ROTATION_TOLERANCE or np.linalg.det(R) <= 0:
            raise ValueError(f"rotation must be orthonormal with det +1 to float64's rounding (|RᵀR − I| ≤ "
                             f"{ROTATION_TOLERANCE:.1e}; this one is {off:.1e} off); build it with "
                             "Transform.from_rotvec or scipy.spatial.transform.Rotation(...).as_matrix()")
        tau = np.asarray(translation, np.float64)
        if tau.shape != (3,) or not np.all(np.isfinite(tau)):
            raise ValueError(f"translation must be 3 finite numbers, got {translation!r}")
        self.child, self.rotation, self.translation = child, R, tau

    @classmethod
    def from_rotvec(cls, child: Field, rotvec=(0.0, 0.0, 0.0), translation=(0.0, 0.0, 0.0)) -> "Transform":
        """Rotation about the axis of ``rotvec`` by |rotvec| radians (scipy's Rotation)."""
        from scipy.spatial.transform import Rotation

        return cls(child, Rotation.from_rotvec(np.asarray(rotvec, float)).as_matrix(), translation)

    @property
    def children(self):
        return (self.child,)

    def own_params(self):
        return {"translation": self.translation.copy()}

    def spec(self) -> dict:
        s = super().spec()
        s["rotation"] = self.rotation.tolist()
        return s

    @property
    def info(self):
        return dataclasses.replace(self.child.info)

    def bounding_sphere(self):
        b = self.child.bounding_sphere()
        return None if b is None else (self.rotation @ b[0] + self.translation, b[1])

    def ray_bounds(self, xp, o, d):
        R = const(xp, o, self.rotation)  # a rigid motion keeps t: bound the local ray
        return self.child.ray_bounds(xp, xp.matmul(o - const(xp, o, self.translation), R), xp.matmul(d, R))

    def _rebuild(self, own, children):
        return Transform(children[0], self.rotation, own["translation"])

    def _local(self, x):
        return (np.asarray(x, np.float64) - self.translation) @ self.rotation

    def _eval(self, x, xp, cursor):
        tau = cursor.take(self.translation)
        return self.child._eval(xp.matmul(x - tau, const(xp, x, self.rotation)), xp, cursor)

    def _jet(self, x):
        phi, g, dth = self.child._jet(self._local(x))
        g = g @ self.rotation.T
        return phi, g, np.concatenate([-g, dth], axis=1)

    def curvatures_exact(self, x):
        return self.child.curvatures_exact(self._local(_points(x)))

    def ray_intervals(self, o, d):
        return self.child.ray_intervals(self._local(_points(o, "o")), _points(d, "d") @ self.rotation)

    def ray_interval_batch(self, o, d):
        return self.child.ray_interval_batch(self._local(_points(o, "o")), _points(d, "d") @ self.rotation)

    def first_hit(self, o, d, t_min: float = 0.0):
        return self.child.first_hit(self._local(_points(o, "o")), _points(d, "d") @ self.rotation, t_min)
