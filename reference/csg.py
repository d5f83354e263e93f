"""Constructive solid geometry on implicit functions (lecture, "Properties - Boolean").

union φ = min(φ₁, φ₂, …), intersection φ = max(…), complement φ = −φ₁, difference
φ = max(φ₁, −φ₂).  These give exactly the stated regions, but the result is in general only a
*distance bound* (|φ| ≤ distance, same sign), not an exact SDF: e.g. inside a union, or
outside an intersection near its edges.  The complement of an exact SDF is an exact SDF.
A min/max of L-Lipschitz functions is L-Lipschitz, so L = max of the children's.

Exact answers: ray intervals by interval set operations on the children's exact intervals
(:mod:`reference.intervals`), so CSG hits are the children's exact hits; the jet, normal and
curvature of the *active* child (the one attaining the min/max; at a seam either one).
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from . import intervals as iv
from . import raybounds
from .scene import Field, SceneInfo, enclosing_ball


def _combine_info(children, exact_sdf=False) -> SceneInfo:
    infos = [c.info for c in children]
    ls = [i.lipschitz for i in infos]
    domains = sorted({i.domain for i in infos if i.domain})
    return SceneInfo(
        exact_sdf=exact_sdf,
        lipschitz=None if any(v is None for v in ls) else max(ls),
        distance_bound=all(i.distance_bound for i in infos),
        smooth=False,
        exact_hits=all(i.exact_hits for i in infos),
        exact_normals=all(i.exact_normals for i in infos),
        exact_curvature=all(i.exact_curvature for i in infos),
        exact_hit_param_grad=all(i.exact_hit_param_grad for i in infos),
        domain=" and ".join(domains) or None,
    )


def _check_children(kids) -> tuple[Field, ...]:
    kids = tuple(kids)
    if len(kids) < 1 or not all(isinstance(k, Field) for k in kids):
        raise ValueError(f"CSG children must be scene nodes (Field), got {[type(k).__name__ for k in kids]}")
    return kids


class _Combination(Field):
    """A CSG node over several children: θ = the children's θ in order, no own parameters."""

    _children: tuple[Field, ...] = ()

    @property
    def children(self):
        return self._children

    @property
    def info(self):
        return _combine_info(self._children)

    def _rebuild(self, own, children):
        return type(self)(*children)


#: the fewest operands of a union (:meth:`Union.operands`) bounded by their balls in one computation
#: (:meth:`Union.ray_bounds`)
MANY_BOUNDS = 8


class _NAry(_Combination):
    """min (union) or max (intersection) over the children."""

    _pick = None  # np.argmin / np.argmax
    _batch_op = None
    _xp_op = ""  # "minimum" / "maximum"

    def __init__(self, *children: Field):
        self._children = _check_children(children)
        if len(self._children) < 2:
            raise ValueError(f"{type(self).__name__} needs at least two children, got {len(self._children)}")

    def _eval(self, x, xp, cursor):
        op = getattr(xp, self._xp_op)
        out = self._children[0]._eval(x, xp, cursor)
        for c in self._children[1:]:
            out = op(out, c._eval(x, xp, cursor))
        return out

    def _active(self, x):
        """Index of the active child per point and every child's jet."""
        jets = [c._jet(x) for c in self._children]
        k = type(self)._pick(np.stack([j[0] for j in jets], axis=1), axis=1)
        return k, jets

    def _jet(self, x):
        k, jets = self._active(x)
        rows = np.arange(x.shape[0])
        phi = np.stack([j[0] for j in jets], axis=1)[rows, k]
        g = np.stack([j[1] for j in jets], axis=1)[rows, k]
        blocks = []
        for i, j in enumerate(jets):
            blocks.append(np.where((k == i)[:, None], j[2], 0.0))
        return phi, g, np.concatenate(blocks, axis=1)

    def curvatures_exact(self, x):
        k, _ = self._active(np.asarray(x, np.float64))
        k1 = np.full(k.shape, np.nan)
        k2 = np.full(k.shape, np.nan)
        for i, c in enumerate(self._children):
            sel = k == i
            if sel.any():
                k1[sel], k2[sel] = c.curvatures_exact(np.asarray(x, np.float64)[sel])
        return k1, k2

    def ray_interval_batch(self, o, d):
        return functools.reduce(type(self)._batch_op, (c.ray_interval_batch(o, d) for c in self._children))


class Union(_NAry):
    """Union of the children's interiors: φ = min(φ₁, φ₂, …)."""

    kind = "union"
    _pick = staticmethod(np.argmin)
    _batch_op = staticmethod(iv.batch_union)
    _xp_op = "minimum"

    def bounding_sphere(self):
        return enclosing_ball(c.bounding_sphere() for c in self._children)

    def operands(self) -> tuple[Field, ...]:
        """The children, with every child that is itself a union replaced by its operands: the
        union's operands as one n-ary min (a union built pairwise, ``functools.reduce(Union, …)``,
        has as many as one built at once)."""
        out = []
        for c in self._children:
            out.extend(c.operands() if type(c) is Union else (c,))
        return tuple(out)

    def ray_bounds(self, xp, o, d):
        """The hull of the children's bounds; with :data:`MANY_BOUNDS` operands or more
        (:meth:`operands`), those with a bounding ball are bounded by its chord, all in one
        computation (:func:`reference.raybounds.balls_chord_hull`): looser for a box or a torus,
        the same for a sphere, and one expression whatever the number of operands."""
        kids = self.operands()
        if len(kids) < MANY_BOUNDS:
            return raybounds.hull(xp, *(c.ray_bounds(xp, o, d) for c in self._children))
        balls = [c.bounding_sphere() for c in kids]
        parts = [c.ray_bounds(xp, o, d) for c, b in zip(kids, balls) if b is None]
        inside = [b for b in balls if b is not None]
        if inside:
            parts.append(raybounds.balls_chord_hull(xp, o, d, np.stack([np.asarray(b[0], np.float64) for b in inside]),
                                                    np.array([float(b[1]) for b in inside])))
        return raybounds.hull(xp, *parts) if len(parts) > 1 else parts[0]



class Intersection(_NAry):
    """Intersection of the children's interiors: φ = max(φ₁, φ₂, …)."""

    kind = "intersection"
    _pick = staticmethod(np.argmax)
    _batch_op = staticmethod(iv.batch_intersection)
    _xp_op = "maximum"

    def bounding_sphere(self):
        balls = [b for b in (c.bounding_sphere() for c in self._children) if b is not None]
        return min(balls, key=lambda b: b[1]) if balls else None

    def ray_bounds(self, xp, o, d):
        return raybounds.meet(xp, *(c.ray_bounds(xp, o, d) for c in self._children))



class Complement(Field):
    """Complement of the child's interior: φ = −φ₁.  Curvatures (−κ2, −κ1) (the outward normal
    flips).  An exact SDF stays exact."""

    kind = "complement"

    def __init__(self, child: Field):
        (self.child,) = _check_children([child])

    @property
    def children(self):
        return (self.child,)

    @property
    def info(self):
        return dataclasses.replace(self.child.info)

    def _rebuild(self, own, children):
        return Complement(children[0])

    def _eval(self, x, xp, cursor):
        return -self.child._eval(x, xp, cursor)

    def _jet(self, x):
        phi, g, dth = self.child._jet(x)
        return -phi, -g, -dth

    def curvatures_exact(self, x):
        k1, k2 = self.child.curvatures_exact(x)
        return -k2, -k1

    def ray_interval_batch(self, o, d):
        return iv.batch_complement(self.child.ray_interval_batch(o, d))


class Difference(_Combination):
    """a minus b: φ = max(φ_a, −φ_b) (children (a, b), θ = (θ_a, θ_b))."""

    kind = "difference"

    def __init__(self, a: Field, b: Field):
        self._children = _check_children([a, b])
        self._as_intersection = Intersection(a, Complement(b))

    def _eval(self, x, xp, cursor):
        a, b = self._children
        return xp.maximum(a._eval(x, xp, cursor), -b._eval(x, xp, cursor))

    def _jet(self, x):  # Complement adds no parameters, so θ order is (θ_a, θ_b) as required
        return self._as_intersection._jet(x)

    def curvatures_exact(self, x):
        return self._as_intersection.curvatures_exact(x)

    def ray_interval_batch(self, o, d):
        return self._as_intersection.ray_interval_batch(o, d)

    def bounding_sphere(self):
        return self._as_intersection.bounding_sphere()  # a's ball (a complement is unbounded)

    def ray_bounds(self, xp, o, d):
        return self._as_intersection.ray_bounds(xp, o, d)  # a's bound
