"""Bounding spheres (``Field.bounding_sphere``): every point where φ ≤ 0 lies in the ball.

The root finders skip everything outside the ball, so a ball that is too small would turn hits
into misses; these tests check the containment on every case and on random CSG trees, both
against the exact ray intervals and by sampling φ outside the ball."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from reference import Sphere
from reference.cases import case_ids, get_case
from reference.csg import Complement, Difference, Intersection, Union
from reference.implicits import Scaled
from reference.numerical import CallableField
from reference.transform import Transform
from test_reference_hits import _placements, _primitive


def _outside_samples(ball, n, rng):
    """Points in the shell between 1 and 4 ball radii (just outside the ball included)."""
    c, r = ball
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    rad = r * np.concatenate([1 + np.geomspace(1e-9, 1e-2, n // 2), rng.uniform(1.01, 4.0, n - n // 2)])
    return c + rad[:, None] * u


def _check_ball(scene, o, d, rng):
    ball = scene.bounding_sphere()
    if ball is None:
        return False
    c, r = ball
    assert np.asarray(c).shape == (3,) and np.all(np.isfinite(c)) and r > 0
    x = _outside_samples(ball, 4000, rng)
    phi = scene.value(x)
    assert np.all(phi > 0), f"φ ≤ 0 outside the bounding ball at {x[np.argmin(phi)]} (φ = {phi.min():.3g})"
    if scene.info.exact_hits:
        for oi, di, bnd in zip(o, d, scene.ray_intervals(o, d)):
            bnd = bnd[np.isfinite(bnd)]
            pts = oi + bnd[:, None] * di
            # rounding of o + t d: a few ulp of |o| + |t|
            slack = r * 1e-12 + 8 * np.finfo(float).eps * (np.linalg.norm(oi) + np.abs(bnd))
            assert np.all(np.linalg.norm(pts - c, axis=1) <= r + slack), "a surface crossing outside the ball"
    return True


@pytest.mark.parametrize("cid", case_ids())
def test_every_case_ball_contains_its_solid(cid):
    case = get_case(cid)
    rng = np.random.default_rng(0)
    if _check_ball(case.scene, case.origins, case.directions, rng):
        hit = np.isfinite(case.exact_t) if case.scene.info.exact_hits else np.zeros(case.n_rays, bool)
        x = case.origins[hit] + case.exact_t[hit, None] * case.directions[hit]
        c, r = case.scene.bounding_sphere()
        slack = r * 1e-12 + 8 * np.finfo(float).eps * (np.linalg.norm(case.origins[hit], axis=1) + case.exact_t[hit])
        assert np.all(np.linalg.norm(x - c, axis=1) <= r + slack)


def test_balls_of_the_nodes():
    s = Sphere((1.0, 2.0, 3.0), 0.5)
    c, r = s.bounding_sphere()
    assert np.array_equal(c, [1, 2, 3]) and r == 0.5
    assert Complement(s).bounding_sphere() is None
    # a union encloses both; an intersection and a difference keep the (smaller / first) ball
    far = Sphere((-4.0, 0.0, 0.0), 1.0)
    cu, ru = Union(s, far).bounding_sphere()
    for b in (s, far):
        cb, rb = b.bounding_sphere()
        assert np.linalg.norm(cb - cu) + rb <= ru * (1 + 1e-15)
    assert Intersection(far, s).bounding_sphere()[1] == 0.5
    assert Difference(far, s).bounding_sphere()[1] == 1.0
    moved = Transform.from_rotvec(s, (0.0, 0.0, np.pi / 2), (1.0, 0.0, 0.0)).bounding_sphere()
    np.testing.assert_allclose(moved[0], [-1.0, 1.0, 3.0], atol=1e-15)
    assert CallableField(lambda x, xp: x[..., 0]).bounding_sphere() is None
    with pytest.raises(ValueError, match="bounds"):
        CallableField(lambda x, xp: x[..., 0], bounds=((0, 0), 1.0))


@settings(max_examples=40, deadline=None)
@given(_placements, _placements, st.sampled_from(["union", "intersection", "difference", "scaled"]))
def test_property_random_csg_ball_contains_the_solid(p, q, op):
    a = Transform.from_rotvec(_primitive(p[0]), p[1], p[2])
    b = Transform.from_rotvec(_primitive(q[0]), q[1], q[2])
    scene = {"union": lambda: Union(a, b), "intersection": lambda: Intersection(a, b),
             "difference": lambda: Difference(a, b), "scaled": lambda: Scaled(Union(a, b), 0.3)}[op]()
    rng = np.random.default_rng(q[3])
    o = rng.uniform(-3, 3, size=(64, 3))
    d = rng.normal(size=(64, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    assert _check_ball(scene, o, d, rng)
