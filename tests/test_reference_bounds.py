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
from reference.implicits import Ellipsoid, Scaled
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


def _rays_of(case, at_most: int = 4096):
    """The case's rays, every k-th of a camera at scale (tag ``large``: 65 536 or 1 048 576 rays),
    deterministic, so that these per-case checks stay seconds long; and the exact first hits of
    those rays where the scene has closed-form hits (else None)."""
    from reference.cases import LARGE

    idx = np.arange(case.n_rays)
    if LARGE in case.tags and case.n_rays > at_most:
        idx = idx[:: -(-case.n_rays // at_most)]
    o, d = case.origins[idx], case.directions[idx]
    t = None
    if case.scene.info.exact_hits:
        t = case.exact_t[idx] if idx.size == case.n_rays else case.scene.first_hit(o, d, case.t_min)
        t = np.where(t <= case.t_max, t, np.inf)
    return o, d, t


@pytest.mark.parametrize("cid", case_ids())
def test_every_case_ball_contains_its_solid(cid):
    case = get_case(cid)
    rng = np.random.default_rng(0)
    o, d, t = _rays_of(case)
    if _check_ball(case.scene, o, d, rng) and t is not None:
        hit = np.isfinite(t)
        x = o[hit] + t[hit, None] * d[hit]
        c, r = case.scene.bounding_sphere()
        slack = r * 1e-12 + 8 * np.finfo(float).eps * (np.linalg.norm(o[hit], axis=1) + t[hit])
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


def _random_csg(p, q, op):
    """Two randomly placed primitives combined by ``op``."""
    a = Transform.from_rotvec(_primitive(p[0]), p[1], p[2])
    b = Transform.from_rotvec(_primitive(q[0]), q[1], q[2])
    return {"union": lambda: Union(a, b), "intersection": lambda: Intersection(a, b),
            "difference": lambda: Difference(a, b), "scaled": lambda: Scaled(Union(a, b), 0.3)}[op]()


_OPS = st.sampled_from(["union", "intersection", "difference", "scaled"])


@settings(max_examples=40, deadline=None)
@given(_placements, _placements, _OPS)
def test_property_random_csg_ball_contains_the_solid(p, q, op):
    scene = _random_csg(p, q, op)
    rng = np.random.default_rng(q[3])
    o = rng.uniform(-3, 3, size=(64, 3))
    d = rng.normal(size=(64, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    assert _check_ball(scene, o, d, rng)


# -- ray bounds (Field.ray_bounds): per-ray intervals that contain the solid's part of the ray ---


def _check_ray_bounds(scene, o, d, rng):
    """Every exact interval boundary lies inside [lo, hi]; φ > 0 at sampled depths outside it
    (1e-9 to 3 beyond its ends); a ray with an empty bound has no crossing and φ > 0 all along
    it (sampled).  Returns the fraction of rays with an empty bound."""
    lo, hi = scene.ray_bounds(np, o, d)
    assert lo.shape == hi.shape == (o.shape[0],) and not np.any(np.isnan(lo) | np.isnan(hi))
    empty = ~(lo <= hi)
    if scene.info.exact_hits:
        for i, bnd in enumerate(scene.ray_intervals(o, d)):
            bnd = bnd[np.isfinite(bnd)]
            assert not (empty[i] and bnd.size), f"ray {i}: the bound is empty but the ray crosses at {bnd}"
            assert np.all((bnd >= lo[i]) & (bnd <= hi[i])), f"ray {i}: crossings {bnd} outside [{lo[i]}, {hi[i]}]"
    off = np.concatenate([np.geomspace(1e-9, 1.0, 12), rng.uniform(0, 3, 4)])
    for side, end in ((-1, lo), (1, hi)):
        ok = np.isfinite(end)
        t = end[ok, None] + side * off[None, :]
        x = o[ok, None, :] + t[..., None] * d[ok, None, :]
        phi = scene.value(x.reshape(-1, 3))
        assert np.all(phi > 0), f"φ = {phi.min():.3g} ≤ 0 outside the ray bound"
    # rays with an empty bound: φ > 0 all along them (sampled)
    if empty.any():
        t = np.linspace(-4, 8, 200)
        x = o[empty, None, :] + t[None, :, None] * d[empty, None, :]
        assert np.all(scene.value(x.reshape(-1, 3)) > 0)
    return float(empty.mean())


def _rays_at(rng, n=256, spread=2.5):
    o = rng.uniform(-spread, spread, size=(n, 3)) + rng.normal(size=(n, 3)) * 2
    d = rng.normal(size=(n, 3))
    # a quarter of the rays run parallel to a coordinate plane or along an axis (the slab test's
    # division-free branch)
    d[: n // 8, 2] = 0.0
    d[n // 8 : n // 4, :2] = 0.0
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


@pytest.mark.parametrize("cid", case_ids())
def test_every_case_ray_bounds_contain_the_solid(cid):
    case = get_case(cid)
    rng = np.random.default_rng(1)
    o, d, _ = _rays_of(case)
    _check_ray_bounds(case.scene, o, d, rng)
    o, d = _rays_at(rng)
    _check_ray_bounds(case.scene, o, d, rng)


def test_ray_bounds_of_the_nodes_are_tight_where_they_can_be():
    """A box's bound is its slab test; a torus's excludes the space above and below it; a union's
    is the hull of its children's; an unbounded solid has no bound."""
    from reference import Box, Plane, Torus

    rng = np.random.default_rng(2)
    o, d = _rays_at(rng, 2000)
    box = Box((0.5, 0.2, 0.3))
    lo, hi = box.ray_bounds(np, o, d)
    for i, bnd in enumerate(box.ray_intervals(o, d)):
        if bnd.size:
            np.testing.assert_allclose([lo[i], hi[i]], [bnd[0], bnd[-1]], atol=1e-5)
        else:
            assert not lo[i] <= hi[i]
    # a ray in the plane z = 0.3 > r passes through the torus's ball, above the tube
    torus = Torus(1.0, 0.25)
    lo, hi = torus.ray_bounds(np, np.array([[-3.0, 0.0, 0.3]]), np.array([[1.0, 0.0, 0.0]]))
    assert not lo[0] <= hi[0]
    # the union's bound is exactly the hull of its children's: from the first entry to the last
    # exit of the non-empty ones, and empty (+inf, −inf) where both are
    far = Transform(Sphere(radius=0.5), translation=(6.0, 0.0, 0.0))
    o = np.concatenate([o, [[-3.0, 0.0, 0.0], [-3.0, 0.1, -0.1]]])  # two rays through both
    d = np.concatenate([d, [[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]])
    lo, hi = Union(box, far).ray_bounds(np, o, d)
    (a1, b1), (a2, b2) = box.ray_bounds(np, o, d), far.ray_bounds(np, o, d)
    e1, e2 = ~(a1 <= b1), ~(a2 <= b2)
    assert (e1 & e2).any() and (~e1 & ~e2).any() and (e1 ^ e2).any()
    np.testing.assert_array_equal(lo, np.where(e1, a2, np.where(e2, a1, np.minimum(a1, a2))))
    np.testing.assert_array_equal(hi, np.where(e1, b2, np.where(e2, b1, np.maximum(b1, b2))))
    assert np.all(np.isposinf(lo[e1 & e2]) & np.isneginf(hi[e1 & e2]))
    lo, hi = Union(box, Plane()).ray_bounds(np, o, d)
    assert np.all(np.isneginf(lo) & np.isposinf(hi))
    assert _check_ray_bounds(Complement(box), o, d, rng) == 0.0


@settings(max_examples=40, deadline=None)
@given(_placements, _placements, _OPS)
def test_property_random_csg_ray_bounds_contain_the_solid(p, q, op):
    scene = _random_csg(p, q, op)
    rng = np.random.default_rng(q[3])
    o, d = _rays_at(rng, 96)
    _check_ray_bounds(scene, o, d, rng)


@pytest.mark.parametrize("backend", ["torch", "jax"])
def test_ray_bounds_agree_across_array_libraries(backend):
    """torch and jax (jitted) give numpy's bounds in float64; in float32 (a larger pad) their
    bounds still contain every exact crossing of the float32 rays."""
    case = get_case("csg.union.camera.32x32")
    scene = Union(case.scene, Transform.from_rotvec(Ellipsoid(), (0.3, 0.1, 0.0), (0.5, 0.0, 1.0)))
    rng = np.random.default_rng(4)
    o, d = _rays_at(rng, 512)
    if backend == "torch":
        torch = pytest.importorskip("torch")
        from array_api_compat import torch as xt

        def bounds(o, d):
            return [g.double().numpy() for g in scene.ray_bounds(xt, torch.from_numpy(o), torch.from_numpy(d))]
    else:
        jax = pytest.importorskip("jax")
        import jax.numpy as jnp

        jax.config.update("jax_enable_x64", True)  # as the jax backend does

        def bounds(o, d):
            return [np.asarray(g, np.float64) for g in jax.jit(lambda o, d: scene.ray_bounds(jnp, o, d))(o, d)]
    for g, w in zip(bounds(o, d), scene.ray_bounds(np, o, d)):
        np.testing.assert_array_equal(np.isfinite(g), np.isfinite(w))
        same = np.isfinite(w)
        np.testing.assert_allclose(g[same], w[same], rtol=1e-9, atol=1e-12)
    o32, d32 = o.astype(np.float32), d.astype(np.float32)
    lo, hi = bounds(o32, d32)
    for i, bnd in enumerate(scene.ray_intervals(o32.astype(np.float64), d32.astype(np.float64))):
        bnd = bnd[np.isfinite(bnd)]
        assert np.all((bnd >= lo[i]) & (bnd <= hi[i])), f"ray {i}: crossings {bnd} outside [{lo[i]}, {hi[i]}]"


@pytest.mark.parametrize("cid", ["csg.union.camera.32x32", "box.camera.32x32", "sphere.camera.64x64"])
def test_ray_bounds_keep_the_working_dtype(cid):
    case = get_case(cid)
    for dt in (np.float32, np.float64):
        lo, hi = case.scene.ray_bounds(np, case.origins.astype(dt), case.directions.astype(dt))
        assert lo.dtype == dt and hi.dtype == dt


@pytest.mark.parametrize("c", [1e3, 1e5, 1e7])
def test_float32_bounds_cover_the_rounding_of_the_rays_themselves(c):
    """A scene far from the origin of its frame, seen from close by: in float32 the rays' origins
    round by up to ε·c/2 in the scene's frame, which no leaf's own pad sees (its |o| is small).
    Under ``raybounds.scene_rays`` (as the root finders compute them) the float32 bounds of the
    rounded rays contain every exact crossing of the float64 rays, for a sphere centred there, a
    translated and rotated torus and a box; float64 bounds are unchanged by it."""
    from reference import Box, Torus, raybounds, rays

    scenes = [Sphere(center=(c, 0.0, 0.0), radius=1.0),
              Transform.from_rotvec(Torus(1.0, 0.2), (0.4, 0.3, 0.0), (c, 0.0, 0.0)),
              Transform(Box((0.5, 0.7, 0.3)), translation=(c, 0.0, 0.0))]
    o, d = rays.pinhole(eye=(c + 0.3, 0.2, 3.0), look_at=(c, 0.0, 0.0), fov_deg=60, width=64, height=64)
    o32, d32 = o.astype(np.float32), d.astype(np.float32)
    for scene in scenes:
        with raybounds.scene_rays(np, o32):
            lo, hi = (np.asarray(v, np.float64) for v in scene.ray_bounds(np, o32, d32))
        for i, bnd in enumerate(scene.ray_intervals(o, d)):
            bnd = bnd[np.isfinite(bnd)]
            assert np.all((bnd >= lo[i]) & (bnd <= hi[i])), (type(scene).__name__, i, bnd, lo[i], hi[i])
        with raybounds.scene_rays(np, o):
            inside = scene.ray_bounds(np, o, d)
        for a, b in zip(inside, scene.ray_bounds(np, o, d)):
            np.testing.assert_array_equal(a, b)


def _many(k, seed=5):
    """A union of k children of four kinds, most off-centre or turned (each has a ball)."""
    from reference import Box, Torus
    from reference.primitives import CappedCylinder

    rng = np.random.default_rng(seed)
    kids = []
    for i in range(k):
        at = tuple(rng.uniform(-1.5, 1.5, 3))
        kind = i % 4
        if kind == 0:
            kids.append(Sphere(center=at, radius=float(rng.uniform(0.05, 0.3))))
        elif kind == 1:
            kids.append(Transform.from_rotvec(Torus(0.3, 0.08), tuple(rng.normal(size=3)), at))
        elif kind == 2:
            kids.append(Transform(Box((0.2, 0.1, 0.15)), translation=at))
        else:
            kids.append(Transform.from_rotvec(CappedCylinder(0.1, 0.25), tuple(rng.normal(size=3)), at))
    return Union(*kids)


@pytest.mark.parametrize("k", [8, 13, 100])
def test_a_union_of_many_children_is_bounded_by_their_balls(k, monkeypatch):
    """From ``csg.MANY_BOUNDS`` children on, a union's bound is the hull of its children's balls'
    chords, computed as one (n, k) expression: bit for bit the hull of :func:`ball_chord` over the
    balls, the same in blocks of balls, and it contains the solid (exact crossings, φ sampled
    beyond its ends).  Fewer children keep their own bounds."""
    from reference import csg, raybounds

    assert 8 >= csg.MANY_BOUNDS
    scene = _many(k)
    rng = np.random.default_rng(k)
    o, d = _rays_at(rng, 512)
    lo, hi = scene.ray_bounds(np, o, d)
    balls = [c.bounding_sphere() for c in scene.children]
    want = raybounds.hull(np, *(raybounds.ball_chord(np, o, d, c, float(r)) for c, r in balls))
    np.testing.assert_array_equal(lo, want[0])
    np.testing.assert_array_equal(hi, want[1])
    monkeypatch.setattr(raybounds, "BALLS_BLOCK", 3 * o.shape[0])  # blocks of 3 balls
    blocked = scene.ray_bounds(np, o, d)
    np.testing.assert_array_equal(blocked[0], lo)
    np.testing.assert_array_equal(blocked[1], hi)
    assert 0.05 < _check_ray_bounds(scene, o, d, rng) < 0.95
    # a union built pair by pair has the same operands, and the same bound
    import functools

    pairwise = functools.reduce(Union, scene.children)
    assert pairwise.operands() == scene.children
    for g, w in zip(pairwise.ray_bounds(np, o, d), (lo, hi)):
        np.testing.assert_array_equal(g, w)
    few = Union(*scene.children[: csg.MANY_BOUNDS - 1])
    exact = raybounds.hull(np, *(c.ray_bounds(np, o, d) for c in few.children))
    np.testing.assert_array_equal(few.ray_bounds(np, o, d)[0], exact[0])
    # a child without a ball (a half-space) keeps its own bound: the union's is then the whole line
    lo, hi = Union(*scene.children, Complement(Sphere())).ray_bounds(np, o, d)
    assert np.all(np.isneginf(lo) & np.isposinf(hi))


def test_the_bound_of_many_children_is_one_expression_under_jit():
    """Under jax the bound of a union of many children lowers to a program of the same size
    whatever their number: a union of 100 spheres had compiled each child's chord into every use
    of the bound (hybrid_secant: 211 s of compilation on a 2-core machine).  In float32 it still
    contains every exact crossing of the rounded rays."""
    jax = pytest.importorskip("jax")
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)  # as the jax backend does
    rng = np.random.default_rng(7)
    o, d = _rays_at(rng, 256)
    sizes = {}
    import functools

    for k in (8, 64, "64 pairwise"):
        scene = _many(64) if k == "64 pairwise" else _many(k)
        if k == "64 pairwise":
            scene = functools.reduce(Union, scene.children)
        fn = jax.jit(lambda o, d, scene=scene: scene.ray_bounds(jnp, o, d))
        sizes[k] = len(fn.lower(o, d).as_text().splitlines())
        got = [np.asarray(g) for g in fn(o, d)]
        want = scene.ray_bounds(np, o, d)
        for g, w in zip(got, want):
            np.testing.assert_allclose(g, w, rtol=1e-12, atol=1e-12)
        o32, d32 = o.astype(np.float32), d.astype(np.float32)
        lo, hi = [np.asarray(g, np.float64) for g in fn(o32, d32)]
        for i, bnd in enumerate(scene.ray_intervals(o32.astype(np.float64), d32.astype(np.float64))):
            bnd = bnd[np.isfinite(bnd)]
            assert np.all((bnd >= lo[i]) & (bnd <= hi[i])), f"ray {i}: crossings {bnd} outside [{lo[i]}, {hi[i]}]"
    assert sizes[64] == sizes[8] == sizes["64 pairwise"], sizes
