"""The batch form of the ray interval algebra (:class:`reference.intervals.IntervalBatch`) gives
the per-ray specification's sets bit for bit (:func:`reference.intervals.union`,
:func:`~reference.intervals.intersection`, :func:`~reference.intervals.complement`): on random
sets drawn from a small grid of boundaries (so that entries, exits and touching ends coincide
often) with ±inf ends, and on the exact intervals of CSG trees no case of the catalog holds."""

from __future__ import annotations

import functools

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from reference import intervals as iv
from reference.csg import Complement, Difference, Intersection, Union
from reference.primitives import Box, Capsule, Plane, Sphere, Torus
from reference.transform import Transform

BOUNDS = [-np.inf, np.inf, -2.0, -1.0, -0.5, 0.0, 0.5, 1.0, 1.5, 2.0, 3.0]


@st.composite
def interval_sets(draw):
    """A valid set (sorted, disjoint, not touching): the union, by the specification, of up to
    five random intervals with ends on :data:`BOUNDS`."""
    out = iv.EMPTY
    for _ in range(draw(st.integers(0, 5))):
        a, b = sorted(draw(st.sampled_from(BOUNDS)) for _ in range(2))
        if a < b:
            out = iv.union(out, np.array([a, b]))
    return out


rays_of_sets = st.lists(interval_sets(), min_size=0, max_size=12)


def same(got: list[np.ndarray], want: list[np.ndarray]) -> None:
    assert len(got) == len(want)
    for g, w in zip(got, want):
        assert g.dtype == np.float64 and g.shape == w.shape and np.array_equal(g, w), (g, w)


@given(rays_of_sets, rays_of_sets)
def test_batch_operations_give_the_specifications_sets(a, b):
    n = min(len(a), len(b))
    a, b = a[:n], b[:n]
    ba, bb = iv.batch_from_list(a), iv.batch_from_list(b)
    same(iv.batch_to_list(ba), a)
    same(iv.batch_to_list(iv.batch_union(ba, bb)), [iv.union(x, y) for x, y in zip(a, b)])
    same(iv.batch_to_list(iv.batch_intersection(ba, bb)), [iv.intersection(x, y) for x, y in zip(a, b)])
    same(iv.batch_to_list(iv.batch_complement(ba)), [iv.complement(x) for x in a])
    for t_min in (-np.inf, -1.0, 0.0, 0.7):
        want = [min((t for t in x if np.isfinite(t) and t > t_min), default=np.inf) for x in a]
        np.testing.assert_array_equal(iv.batch_first_crossing(ba, t_min), np.array(want, np.float64))


def test_bounds_with_nan_or_no_room_are_empty():
    t0 = np.array([0.0, np.nan, 2.0, 1.0, -np.inf, 1.0])
    t1 = np.array([1.0, 1.0, 1.0, np.nan, np.inf, 1.0])
    same(iv.batch_to_list(iv.batch_from_bounds(t0, t1)), iv.from_bounds(t0, t1))
    assert iv.batch_from_bounds(t0, t1).counts.tolist() == [1, 0, 0, 0, 1, 0]


def test_a_ray_with_an_odd_number_of_boundaries_is_refused_by_name():
    with pytest.raises(ValueError, match=r"ray_intervals: ray 1 has 3 boundaries"):
        iv.batch_from_list([np.array([0.0, 1.0]), np.array([0.0, 1.0, 2.0])])


def _per_ray(node, o, d) -> list[np.ndarray]:
    """The node's intervals by the per-ray specification (its leaves' own intervals combined ray
    by ray), independent of the batch code that :meth:`ray_intervals` now runs."""
    if isinstance(node, (Union, Intersection)):
        op = iv.union if isinstance(node, Union) else iv.intersection
        kids = [_per_ray(c, o, d) for c in node.children]
        return [functools.reduce(op, ray) for ray in zip(*kids)]
    if isinstance(node, Difference):
        a, b = (_per_ray(c, o, d) for c in node.children)
        return [iv.difference(x, y) for x, y in zip(a, b)]
    if isinstance(node, Complement):
        return [iv.complement(x) for x in _per_ray(node.child, o, d)]
    return node.ray_intervals(o, d)  # a leaf (or a transform of one): its closed-form set


@pytest.mark.parametrize("seed", range(6))
def test_csg_trees_give_the_per_ray_algebras_intervals(seed):
    rng = np.random.default_rng(seed)
    leaves = [Sphere(center=tuple(rng.uniform(-0.5, 0.5, 3)), radius=rng.uniform(0.2, 0.8)),
              Transform.from_rotvec(Box(tuple(rng.uniform(0.1, 0.6, 3))), tuple(rng.normal(size=3)),
                                    tuple(rng.uniform(-0.3, 0.3, 3))),
              Transform.from_rotvec(Torus(0.5, 0.15), tuple(rng.normal(size=3)), (0.0, 0.0, 0.0)),
              Capsule(a=(-0.4, 0.0, 0.0), b=(0.4, 0.2, 0.1), radius=0.2),
              Plane(normal=(0.0, 0.6, 0.8), offset=rng.uniform(-0.5, 0.5))]
    rng.shuffle(leaves)
    a, b, c, e, f = leaves
    tree = Union(Difference(Union(a, b), Intersection(c, Complement(e))), Complement(f))
    o = rng.normal(size=(3000, 3)) * 2.0
    d = rng.normal(size=(3000, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    same(tree.ray_intervals(o, d), _per_ray(tree, o, d))
