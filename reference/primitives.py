"""Primitive shapes with exact SDFs and exact answers.

Each primitive's ``_eval`` is the textbook SDF (I. Quilez, "distance functions",
https://iquilezles.org/articles/distfunctions/; J. C. Hart, "Sphere tracing", The Visual
Computer 12, 1996), written with array-API functions only.  Exact answers are float64 numpy:
ray intervals from closed-form roots (:mod:`reference.quadric`, :mod:`reference.quartic`,
:mod:`reference.intervals`), and the jet (φ, ∇φ, ∂φ/∂θ) from the differentiated formulas,
from which :class:`Field` derives normals, closest points and dt/dθ.

Principal curvatures use the convention of :mod:`reference.curvature` (κ1 ≥ κ2, positive where
the surface bends away from the outward normal).  Where a surface has an edge (box edges,
cylinder rims) the curvature is undefined and NaN is returned.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from . import intervals as iv
from . import raybounds
from .arrays import const, max_last, norm, safe_norm, sum_last, unit
from .quadric import ray_cylinder_roots, ray_sphere_roots, ray_slab
from .quartic import ray_torus
from .scene import Field, SceneInfo, _points


def _vec3(name: str, v) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be 3 finite numbers, got {v!r}")
    return a


def _positive(name: str, v) -> float:
    try:
        v = float(v)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a finite number > 0, got {v!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be a finite number > 0, got {v!r}")
    return v


def _sdf_info(**kw) -> SceneInfo:
    base = dict(exact_sdf=True, lipschitz=1.0, distance_bound=True, smooth=True, exact_hits=True,
                exact_normals=True, exact_curvature=True, exact_hit_param_grad=True)
    base.update(kw)
    return SceneInfo(**base)


def _sign(x):
    return np.where(x >= 0, 1.0, -1.0)


def _rounded_max_jet(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """ψ(q) = |max(q, 0)| + min(maxᵢ qᵢ, 0) (the box/cylinder SDF in terms of the face
    distances q) and its gradient u = ∂ψ/∂q: max(q, 0)/|max(q, 0)| outside (some qᵢ > 0),
    the unit vector of the largest qᵢ inside and on the surface."""
    mq = np.maximum(q, 0)
    out_len = np.linalg.norm(mq, axis=1)
    outside = np.max(q, axis=1) > 0
    e = np.zeros_like(q)
    e[np.arange(q.shape[0]), np.argmax(q, axis=1)] = 1.0
    with np.errstate(invalid="ignore", divide="ignore"):
        u = np.where(outside[:, None], mq / out_len[:, None], e)
    return out_len + np.minimum(np.max(q, axis=1), 0), u


@dataclasses.dataclass(frozen=True, eq=False)
class Sphere(Field):
    """Sphere of centre c and radius r: φ(x) = |x − c| − r (exact SDF, L = 1).

    Exact answers: first hit by the stable quadratic (:func:`ray_sphere_roots`); normal
    n = (x − c)/|x − c|; principal curvatures κ1 = κ2 = 1/r, so the mean curvature
    H = (κ1 + κ2)/2 = 1/r and the lecture's sum κ1 + κ2 = Δφ = 2/r on the surface.
    Partials ∂φ/∂c = −n, ∂φ/∂r = −1, so (implicit differentiation, |d| = 1)
    dt/dc = n/(n·d) and dt/dr = 1/(n·d).  θ = (c_x, c_y, c_z, r).
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
        return _sdf_info()

    def bounding_sphere(self):
        return np.array(self.center), self.radius

    def _eval(self, x, xp, cursor):
        c = cursor.take(self.own_params()["center"])
        r = cursor.take(self.own_params()["radius"])
        return norm(xp, x - c) - r

    # exact answers -------------------------------------------------------------------------
    def ray_interval_batch(self, o, d):
        return iv.batch_from_bounds(*ray_sphere_roots(o, d, self.center, self.radius))

    def certified_roots(self, o, d):
        """Real roots exist iff the discriminant (f·d)² − (d·d)(f·f − r²), f = o − c, is ≥ 0:
        decided exactly in rationals (``fractions.Fraction`` of the float64 inputs)."""
        from fractions import Fraction as Q

        c, r = [Q(float(v)) for v in np.asarray(self.center, np.float64)], Q(float(self.radius))
        out = np.zeros(np.shape(o)[0], bool)
        for i, (oi, di) in enumerate(zip(np.asarray(o, np.float64), np.asarray(d, np.float64))):
            f = [Q(float(oi[k])) - c[k] for k in range(3)]
            dd = [Q(float(x)) for x in di]
            b = sum(f[k] * dd[k] for k in range(3))
            out[i] = b * b - sum(x * x for x in dd) * (sum(x * x for x in f) - r * r) >= 0
        return out

    def first_hit(self, o, d, t_min: float = 0.0):
        """First root > t_min; a tangent ray (double root) counts as a hit.  Whether a ray whose
        line passes within 1e-7 (relative) of the radius from the centre hits at all is decided
        exactly (:meth:`certified_roots`), not by the rounded discriminant: a near miss the float64
        discriminant calls a touch is a miss, a touch it calls a miss is a hit at −(f·d)/(d·d)."""
        o, d = _points(o, "o"), _points(d, "d")
        t0, t1 = ray_sphere_roots(o, d, self.center, self.radius)
        f = o - np.asarray(self.center, np.float64)
        a = np.einsum("ij,ij->i", d, d)
        b = np.einsum("ij,ij->i", f, d)
        ell = np.linalg.norm(f - (b / a)[:, None] * d, axis=1)
        near = np.flatnonzero(np.abs(ell - self.radius) <= 1e-7 * self.radius)
        if near.size:
            real = self.certified_roots(o[near], d[near])
            centre = -b[near] / a[near]
            t0[near] = np.where(real, np.where(np.isnan(t0[near]), centre, t0[near]), np.nan)
            t1[near] = np.where(real, np.where(np.isnan(t1[near]), centre, t1[near]), np.nan)
        t = np.where(t0 > t_min, t0, np.where(t1 > t_min, t1, np.inf))
        return np.where(np.isnan(t), np.inf, t)

    def _jet(self, x):
        v = x - np.asarray(self.center)
        nv = np.linalg.norm(v, axis=-1)
        n = v / nv[:, None]
        return nv - self.radius, n, np.concatenate([-n, -np.ones((x.shape[0], 1))], axis=1)

    def curvatures_exact(self, x):
        k = np.full(np.shape(x)[:-1], 1.0 / self.radius)
        return k, k.copy()


@dataclasses.dataclass(frozen=True, eq=False)
class Plane(Field):
    """Half-space below a plane: φ(x) = n·x − h, n a fixed unit normal, h the offset (θ = (h,)).

    Exact SDF, L = 1.  Hit t = (h − n·o)/(n·d); ∂φ/∂h = −1 so dt/dh = 1/(n·d).  κ1 = κ2 = 0.
    """

    normal: tuple = (0.0, 0.0, 1.0)
    offset: float = 0.0
    kind = "plane"

    def __post_init__(self):
        nrm = _vec3("normal", self.normal)
        if np.linalg.norm(nrm) == 0:
            raise ValueError("normal must be a non-zero vector, got (0, 0, 0)")
        object.__setattr__(self, "normal", tuple((nrm / np.linalg.norm(nrm)).tolist()))
        off = float(self.offset)
        if not math.isfinite(off):
            raise ValueError(f"offset must be a finite number, got {self.offset!r}")
        object.__setattr__(self, "offset", off)

    def own_params(self):
        return {"offset": np.array(self.offset)}

    @property
    def info(self):
        return _sdf_info()

    def bounding_sphere(self):
        return None  # a half-space

    def _eval(self, x, xp, cursor):
        h = cursor.take(self.own_params()["offset"])
        return sum_last(xp, x * const(xp, x, np.asarray(self.normal))) - h

    def ray_interval_batch(self, o, d):
        o, d = _points(o, "o"), _points(d, "d")
        nv = np.asarray(self.normal)
        nd = d @ nv
        s = self.offset - o @ nv  # n·(x) < h  <=>  t·nd < s
        with np.errstate(divide="ignore", invalid="ignore"):
            t = s / nd
        t0 = np.where(nd > 0, -np.inf, np.where(nd < 0, t, np.where(s > 0, -np.inf, np.nan)))
        t1 = np.where(nd > 0, t, np.where(nd < 0, np.inf, np.where(s > 0, np.inf, np.nan)))
        return iv.batch_from_bounds(t0, t1)

    def _jet(self, x):
        n = x.shape[0]
        return x @ np.asarray(self.normal) - self.offset, np.tile(self.normal, (n, 1)), -np.ones((n, 1))

    def curvatures_exact(self, x):
        z = np.zeros(np.shape(x)[:-1])
        return z, z.copy()


@dataclasses.dataclass(frozen=True, eq=False)
class Box(Field):
    """Axis-aligned box centred at the origin with half-sizes b (θ = (b_x, b_y, b_z)).

    φ(x) = |max(q, 0)| + min(max_i q_i, 0), q = |x| − b (Quilez): exact SDF, L = 1.
    Hits by the slab method (Kay & Kajiya 1986), one correctly rounded division per bound;
    rays parallel to a face handled explicitly.  On a face (q_i = 0 the largest): ∇φ = sign(x_i) e_i,
    ∂φ/∂b_i = −1, κ1 = κ2 = 0; edges and corners have no curvature (NaN).  Place it with
    :class:`reference.transform.Transform`.
    """

    half_size: tuple = (1.0, 1.0, 1.0)
    kind = "box"

    def __post_init__(self):
        b = _vec3("half_size", self.half_size)
        if not np.all(b > 0):
            raise ValueError(f"half_size must be 3 numbers > 0, got {self.half_size!r}")
        object.__setattr__(self, "half_size", tuple(b.tolist()))

    def own_params(self):
        return {"half_size": np.array(self.half_size)}

    @property
    def info(self):
        return _sdf_info(smooth=False)

    def bounding_sphere(self):
        return np.zeros(3), float(np.linalg.norm(self.half_size))

    def ray_bounds(self, xp, o, d):
        return raybounds.box_chord(xp, o, d, self.half_size, self.bounding_sphere()[1])  # the box itself

    def _eval(self, x, xp, cursor):
        b = cursor.take(self.own_params()["half_size"])
        q = xp.abs(x) - b
        zero = const(xp, q, 0.0)
        return safe_norm(xp, xp.maximum(q, zero)) + xp.minimum(max_last(xp, q), const(xp, x[..., 0], 0.0))

    def ray_interval_batch(self, o, d):
        o, d = _points(o, "o"), _points(d, "d")
        lo, hi = np.full(o.shape[0], -np.inf), np.full(o.shape[0], np.inf)
        empty = np.zeros(o.shape[0], bool)
        for i, b in enumerate(self.half_size):
            a0, a1 = ray_slab(o[:, i], d[:, i], -b, b)
            empty |= np.isnan(a0)  # a parallel ray outside this slab: no interval at all
            lo, hi = np.fmax(lo, a0), np.fmin(hi, a1)
        return iv.batch_from_bounds(np.where(empty, np.nan, lo), hi)

    def _jet(self, x):
        b = np.asarray(self.half_size)
        phi, u = _rounded_max_jet(np.abs(x) - b)
        return phi, _sign(x) * u, -u

    def curvatures_exact(self, x):
        x = _points(x)
        q = np.sort(np.abs(x) - np.asarray(self.half_size), axis=1)
        face = (q[:, 2] - q[:, 1]) > 1e-12 * max(self.half_size)
        k = np.where(face, 0.0, np.nan)
        return k, k.copy()


@dataclasses.dataclass(frozen=True, eq=False)
class Torus(Field):
    """Torus about the z axis through the origin: φ(x) = √((ρ − R)² + z²) − r, ρ = √(x² + y²).

    θ = (R, r), R > r > 0.  Exact SDF, L = 1.  Hits: the quartic of :mod:`reference.quartic`,
    polished on the SDF.  With q = (ρ − R, z): ∇φ = ((ρ−R)/|q| · (x, y)/ρ, z/|q|),
    ∂φ/∂R = −(ρ − R)/|q|, ∂φ/∂r = −1.  Principal curvatures at a surface point with tube angle v
    (cos v = (ρ − R)/r): κ_tube = 1/r and κ_ring = cos v / ρ = (ρ − R)/(r ρ) (do Carmo,
    *Differential Geometry of Curves and Surfaces*, §3-3, Example 4): κ1 = 1/r, κ2 = κ_ring,
    positive on the outer equator and −1/(R − r) on the inner one.
    """

    major: float = 1.0
    minor: float = 0.25
    kind = "torus"

    def __post_init__(self):
        R, r = _positive("major", self.major), _positive("minor", self.minor)
        if not r < R:
            raise ValueError(f"minor radius must be < major radius (a ring torus), got major={R}, minor={r}")
        object.__setattr__(self, "major", R)
        object.__setattr__(self, "minor", r)

    def own_params(self):
        return {"major": np.array(self.major), "minor": np.array(self.minor)}

    @property
    def info(self):
        return _sdf_info()

    def bounding_sphere(self):
        return np.zeros(3), self.major + self.minor

    def ray_bounds(self, xp, o, d):
        size = self.major + self.minor  # the ball of radius R + r ∩ the slab |z| ≤ r
        return raybounds.meet(xp, raybounds.ball_chord(xp, o, d, (0.0, 0.0, 0.0), size),
                              raybounds.slab_chord(xp, o, d, 2, self.minor, size))

    def _eval(self, x, xp, cursor):
        R = cursor.take(self.own_params()["major"])
        r = cursor.take(self.own_params()["minor"])
        rho = norm(xp, x[..., 0:2])
        a = rho - R
        z = x[..., 2]
        return xp.sqrt(a * a + z * z) - r

    def _roots(self, o, d):
        return ray_torus(_points(o, "o"), _points(d, "d"), self.major, self.minor)

    def ray_intervals(self, o, d):
        return self._roots(o, d)[0]

    def certified_roots(self, o, d):
        """The exact tangents float64 can name: a ray in the plane z = ±r (d_z = 0 and o_z = ±r
        exactly) has φ = √((ρ − R)² + r²) − r ≥ 0 along it, = 0 where ρ = R; its line meets the
        circle ρ = R iff its distance to the z axis, |o_x d_y − o_y d_x| / |d_xy|, is ≤ R, decided
        exactly in rationals.  Other rays: not proven here (False)."""
        from fractions import Fraction as Q

        o, d = np.asarray(o, np.float64), np.asarray(d, np.float64)
        out = np.zeros(o.shape[0], bool)
        R = Q(float(self.major))
        for i in np.flatnonzero((d[:, 2] == 0) & (np.abs(o[:, 2]) == self.minor)):
            ox, oy, dx, dy = (Q(float(v)) for v in (o[i, 0], o[i, 1], d[i, 0], d[i, 1]))
            m = ox * dy - oy * dx
            out[i] = (dx != 0 or dy != 0) and m * m <= R * R * (dx * dx + dy * dy)
        return out

    def first_hit(self, o, d, t_min: float = 0.0):
        """First crossing or tangent touch (double root) at t > t_min; inf for a miss."""
        cross, tang = self._roots(o, d)
        out = np.full(len(cross), np.inf)
        for i, (c, g) in enumerate(zip(cross, tang)):
            b = np.concatenate([c, g])
            b = b[b > t_min]
            if b.size:
                out[i] = b.min()
        return out

    def _jet(self, x):
        rho = np.hypot(x[:, 0], x[:, 1])
        a = rho - self.major
        ql = np.hypot(a, x[:, 2])
        g = np.stack([a / ql * x[:, 0] / rho, a / ql * x[:, 1] / rho, x[:, 2] / ql], axis=1)
        dth = np.stack([-a / ql, -np.ones_like(a)], axis=1)
        return ql - self.minor, g, dth

    def curvatures_exact(self, x):
        x = _points(x)
        rho = np.hypot(x[:, 0], x[:, 1])
        a = rho - self.major
        cos_v = a / np.hypot(a, x[:, 2])
        return np.full(x.shape[0], 1.0 / self.minor), cos_v / rho


@dataclasses.dataclass(frozen=True, eq=False)
class Capsule(Field):
    """Capsule: points within r of the segment [a, b].  φ(x) = |x − p(x)| − r with
    p(x) = a + h(b − a), h = clamp((x − a)·(b − a)/|b − a|², 0, 1) (Quilez).  Exact SDF, L = 1.

    θ = (a, b, r).  By the envelope theorem (φ = min over the segment): ∂φ/∂a = −u(1 − h),
    ∂φ/∂b = −u h, ∂φ/∂r = −1 with u = (x − p)/|x − p| = ∇φ.  Hits: union of the two end
    spheres and the finite cylinder (interval set union).  Curvatures: (1/r, 0) on the
    cylinder, (1/r, 1/r) on the caps.
    """

    a: tuple = (0.0, 0.0, -0.5)
    b: tuple = (0.0, 0.0, 0.5)
    radius: float = 0.5
    kind = "capsule"

    def __post_init__(self):
        a, b = _vec3("a", self.a), _vec3("b", self.b)
        if np.linalg.norm(b - a) == 0:
            raise ValueError("capsule end points a and b must differ (use Sphere for a ball)")
        object.__setattr__(self, "a", tuple(a.tolist()))
        object.__setattr__(self, "b", tuple(b.tolist()))
        object.__setattr__(self, "radius", _positive("radius", self.radius))

    def own_params(self):
        return {"a": np.array(self.a), "b": np.array(self.b), "radius": np.array(self.radius)}

    @property
    def info(self):
        return _sdf_info()

    def bounding_sphere(self):
        a, b = np.array(self.a), np.array(self.b)
        return 0.5 * (a + b), 0.5 * float(np.linalg.norm(b - a)) + self.radius

    def _eval(self, x, xp, cursor):
        a = cursor.take(self.own_params()["a"])
        b = cursor.take(self.own_params()["b"])
        r = cursor.take(self.own_params()["radius"])
        pa, ba = x - a, b - a
        h = sum_last(xp, pa * ba) / sum_last(xp, ba * ba)
        h = xp.minimum(xp.maximum(h, const(xp, h, 0.0)), const(xp, h, 1.0))
        return norm(xp, pa - h[..., None] * ba) - r

    def _h(self, x):
        a, b = np.asarray(self.a), np.asarray(self.b)
        ba = b - a
        return np.clip((x - a) @ ba / (ba @ ba), 0.0, 1.0)

    def ray_interval_batch(self, o, d):
        o, d = _points(o, "o"), _points(d, "d")
        a, b = np.asarray(self.a), np.asarray(self.b)
        length = np.linalg.norm(b - a)
        u = (b - a) / length
        f = o - a
        fz, dz = f @ u, d @ u
        c0, c1 = ray_cylinder_roots(f - fz[:, None] * u, d - dz[:, None] * u, self.radius)
        s0, s1 = ray_slab(fz, dz, 0.0, length)
        cyl = iv.batch_intersection(iv.batch_from_bounds(c0, c1), iv.batch_from_bounds(s0, s1))
        sa = iv.batch_from_bounds(*ray_sphere_roots(o, d, a, self.radius))
        sb = iv.batch_from_bounds(*ray_sphere_roots(o, d, b, self.radius))
        return iv.batch_union(iv.batch_union(sa, sb), cyl)

    def _jet(self, x):
        a, b = np.asarray(self.a), np.asarray(self.b)
        h = self._h(x)
        v = x - (a + h[:, None] * (b - a))
        nv = np.linalg.norm(v, axis=1)
        u = v / nv[:, None]
        dth = np.concatenate([-u * (1 - h)[:, None], -u * h[:, None], -np.ones((x.shape[0], 1))], axis=1)
        return nv - self.radius, u, dth

    def curvatures_exact(self, x):
        x = _points(x)
        h = self._h(x)
        k1 = np.full(x.shape[0], 1.0 / self.radius)
        return k1, np.where((h > 0) & (h < 1), 0.0, 1.0 / self.radius)


@dataclasses.dataclass(frozen=True, eq=False)
class CappedCylinder(Field):
    """Solid cylinder about the z axis, radius r, |z| ≤ h (θ = (r, h)).

    φ = |max(w, 0)| + min(max(w₁, w₂), 0), w = (ρ − r, |z| − h) (Quilez): exact SDF, L = 1.
    Hits: infinite cylinder (stable quadratic, rays parallel to the axis handled) ∩ slab.  On the
    side: ∇φ = (x, y, 0)/ρ, ∂φ/∂r = −1, κ = (1/r, 0); on a cap: ∇φ = (0, 0, sign z), ∂φ/∂h = −1,
    κ = (0, 0); the rims have no curvature (NaN).
    """

    radius: float = 0.5
    half_height: float = 0.5
    kind = "cylinder"

    def __post_init__(self):
        object.__setattr__(self, "radius", _positive("radius", self.radius))
        object.__setattr__(self, "half_height", _positive("half_height", self.half_height))

    def own_params(self):
        return {"radius": np.array(self.radius), "half_height": np.array(self.half_height)}

    @property
    def info(self):
        return _sdf_info(smooth=False)

    def bounding_sphere(self):
        return np.zeros(3), float(np.hypot(self.radius, self.half_height))

    def ray_bounds(self, xp, o, d):
        r, h = self.radius, self.half_height  # the box |x|, |y| ≤ r, |z| ≤ h around it
        return raybounds.box_chord(xp, o, d, (r, r, h), self.bounding_sphere()[1])

    def _eval(self, x, xp, cursor):
        r = cursor.take(self.own_params()["radius"])
        h = cursor.take(self.own_params()["half_height"])
        w = xp.stack([norm(xp, x[..., 0:2]) - r, xp.abs(x[..., 2]) - h], axis=-1)
        zero = const(xp, w, 0.0)
        return safe_norm(xp, xp.maximum(w, zero)) + xp.minimum(max_last(xp, w), const(xp, x[..., 0], 0.0))

    def ray_interval_batch(self, o, d):
        o, d = _points(o, "o"), _points(d, "d")
        z2 = np.array([1.0, 1.0, 0.0])
        c0, c1 = ray_cylinder_roots(o * z2, d * z2, self.radius)
        s0, s1 = ray_slab(o[:, 2], d[:, 2], -self.half_height, self.half_height)
        return iv.batch_intersection(iv.batch_from_bounds(c0, c1), iv.batch_from_bounds(s0, s1))

    def _w(self, x):
        rho = np.hypot(x[:, 0], x[:, 1])
        return rho, np.stack([rho - self.radius, np.abs(x[:, 2]) - self.half_height], axis=1)

    def _jet(self, x):
        rho, w = self._w(x)
        phi, u = _rounded_max_jet(w)
        with np.errstate(invalid="ignore", divide="ignore"):
            er = np.stack([x[:, 0] / rho, x[:, 1] / rho, np.zeros_like(rho)], axis=1)
        ez = np.stack([np.zeros_like(rho), np.zeros_like(rho), _sign(x[:, 2])], axis=1)
        return phi, u[:, :1] * er + u[:, 1:] * ez, -u

    def curvatures_exact(self, x):
        x = _points(x)
        _, w = self._w(x)
        gap = np.abs(w[:, 0] - w[:, 1]) > 1e-12 * max(self.radius, self.half_height)
        side = w[:, 0] > w[:, 1]
        k1 = np.where(gap, np.where(side, 1.0 / self.radius, 0.0), np.nan)
        return k1, np.where(gap, 0.0, np.nan)


__all__ = ["Box", "CappedCylinder", "Capsule", "Plane", "Sphere", "Torus", "unit"]
