"""The certified root finders' step field (:func:`impls.core.methods_root.step_field`): CSG operands
stepped at their own Lipschitz bounds.  What it must keep (the sign of φ everywhere, a Lipschitz
bound L*) is checked on random points of random scenes, its gain end to end on a scene where one
steep operand stalled every ray before, on every backend."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from impls.core.methods_root import step_field
from impls.protocol import Status
from reference import rays
from reference.cases import DeclaredLipschitz, catalog, get_case
from reference.csg import Complement, Difference, Intersection, Union
from reference.implicits import Ellipsoid, Scaled
from reference.primitives import Box, Sphere
from reference.transform import Transform
from tests.conformance.common import depth_resolved
from tests.conftest import require_method
from tests.test_certified_at_scale import _solve, allowance, check_guarantee, random_camera


def _mixed_leaf(rng):
    """A random leaf of :func:`tests.test_certified_at_scale._random_leaf` whose bound holds
    everywhere (no ellipsoid or algebraic sphere), half of them scaled by k ∈ [0.3, 100]."""
    from tests.test_certified_at_scale import _random_leaf

    leaf = _random_leaf(rng)
    while leaf.info.domain is not None:
        leaf = _random_leaf(rng)
    return Scaled(leaf, float(10 ** rng.uniform(-0.5, 2.0))) if rng.random() < 0.5 else leaf


def _mixed_tree(rng, depth: int):
    if depth == 0 or rng.random() < 0.25:
        return _mixed_leaf(rng)
    op, a, b = int(rng.integers(4)), _mixed_tree(rng, depth - 1), _mixed_tree(rng, depth - 1)
    if op == 3:
        return Union(a, Transform.from_rotvec(b, tuple(rng.normal(size=3)), tuple(rng.uniform(-0.3, 0.3, 3))))
    return (Union, Intersection, Difference)[op](a, b)


@functools.lru_cache(maxsize=None)
def mixed_scene(seed: int, side: int = 256):
    """A seeded random CSG tree whose operands' bounds differ (leaves scaled by up to 100, so the
    step field rewrites it), sometimes complemented, and a camera (:func:`random_camera`):
    ``(scene, o, d, t_min, exact ray intervals)``."""
    rng = np.random.default_rng(1000 + seed)
    scene = _mixed_tree(rng, 3)
    if rng.random() < 0.2:
        scene = Complement(scene)
    return (scene, *random_camera(rng, scene, side))


def assert_sign_and_slope(scene, s, x, y, lstar: float, slack=0.0):
    """sign(s) = sign(φ) at the points ``x``, and every slope of s sampled on the pairs (x, y) at
    most L*·(1 + 10⁻⁹) + ``slack`` (rounding, a number or one per pair).  Returns (φ(x), s(x))."""
    phi, sx, sy = scene.value(x, np), s.value(x, np), s.value(y, np)
    np.testing.assert_array_equal(np.sign(sx), np.sign(phi))
    slope = np.abs(sx - sy) / np.linalg.norm(x - y, axis=1)
    assert np.all(slope <= lstar * (1 + 1e-9) + slack), (slope.max(), lstar)
    return phi, sx


def test_the_catalog_scenes_march_on_themselves():
    """Every catalog scene is a single leaf or its leaves share one bound (with the scalings above
    them) and hold everywhere, so its step field is the scene object itself: the baseline's rows
    cannot move."""
    for case in catalog():
        assert step_field(case.scene) is case.scene, case.id


@pytest.mark.parametrize("seed", range(24))
def test_the_step_field_keeps_the_sign_and_its_bound(seed):
    """On 20,000 random points of a random CSG tree whose operands' bounds differ
    (:func:`mixed_scene`): sign(s) = sign(φ), s is L*-Lipschitz on 20,000 random pairs (L* = the
    step field's stated bound, the sampled slopes below it to rounding), and its step |s|/L* is
    never shorter than |φ|/L."""
    scene = mixed_scene(seed, 2)[0]
    s = step_field(scene)
    if len([n for n in scene.walk() if not n.children]) > 1:
        assert s is not scene or len({n.info.lipschitz for n in scene.walk()}) == 1
    lstar, lip = s.info.lipschitz, scene.info.lipschitz
    assert lstar <= lip * (1 + 1e-15)
    rng = np.random.default_rng(seed)
    x = rng.uniform(-1.5, 1.5, (20000, 3))
    y = x + rng.normal(size=x.shape) * 10 ** rng.uniform(-6, 0, (x.shape[0], 1))
    phi, sx = assert_sign_and_slope(scene, s, x, y, lstar, 1e-12 / np.linalg.norm(x - y, axis=1).min())
    assert np.all(np.abs(sx) / lstar >= np.abs(phi) / lip * (1 - 1e-12))


def test_mixed_bounds_are_normalized_to_the_smallest():
    """A union of a sphere (L = 1) and a box whose stated bound is 800 (a loose bound, as a user's
    may be): the box's φ enters scaled by 1/800, the sphere's unscaled, and the step field states
    L* = 1.  Scalings above the leaves are dropped (they cancel), and a scene whose leaves' bounds
    agree once those scalings are counted is left as it is."""
    loose = DeclaredLipschitz(Box((0.1, 0.5, 0.5)), 800.0)
    ball, placed = Sphere(radius=0.5), Transform.from_rotvec(loose, (0, 0.2, 0), (1.0, 0.0, 0.0))
    scene = Union(ball, placed)
    s = step_field(scene)
    assert scene.info.lipschitz == 800.0 and s.info.lipschitz == 1.0
    scaled = [n for n in s.walk() if type(n) is Scaled]
    assert len(scaled) == 1 and scaled[0].child is loose and scaled[0].scale == 1 / 800
    assert step_field(scene) is s  # computed once per scene object
    x = np.random.default_rng(0).uniform(-2, 2, (1000, 3))
    np.testing.assert_allclose(s.value(x, np), np.minimum(ball.value(x, np), placed.value(x, np) / 800), rtol=1e-15)
    # a box and a sphere both scaled by 2: both operands 2-Lipschitz, nothing to change; the box
    # alone scaled by 2: bounds 2 and 1, so both are stepped at 1 (the scaling dropped)
    same = Union(Scaled(Box((0.2, 0.2, 0.2)), 2.0), Scaled(Sphere(radius=0.3), 2.0))
    assert step_field(same) is same
    mixed = Union(Scaled(Box((0.2, 0.2, 0.2)), 2.0), Sphere(radius=0.3))
    sm = step_field(mixed)
    assert sm is not mixed and sm.info.lipschitz == 1.0 and not any(type(n) is Scaled for n in sm.walk())
    for op in (Intersection, Difference):
        assert step_field(op(Sphere(radius=0.5), loose)).info.lipschitz == 1.0
    assert step_field(Complement(scene)).info.lipschitz == 1.0


def _domain_leaf(leaf: str, radius: float = 1.0):
    """An algebraic sphere or a sphere-like ellipsoid of ``radius`` at the origin: bounds stated on
    |x| ≤ 4 only (L = 8 and 8/r²)."""
    from reference.implicits import AlgebraicSphere

    return AlgebraicSphere(radius=radius) if leaf == "algsphere" else Ellipsoid(axes=(radius,) * 3)


def _leaf_above_a_far_floor(leaf: str, side: int = 256):
    """The leaf (radius 1) over the half-space z ≤ −380, seen from z = 20, outside the leaf's
    domain, 256² rays in 10°, 16,7xx of them on the leaf.  Stepped at φ/L (L = 8), each of those
    rays took one step of about 50 from the camera (φ = min(z² − 1, z + 380) = 399) across the
    leaf to z ≈ −30, where the floor's φ ≈ 350 is the union's and both ends of the step agree
    with L, and CONVERGED on the floor (1,044 of 4,096 at 64², both certified methods)."""
    from reference.primitives import Plane

    scene = Union(_domain_leaf(leaf), Plane(normal=(0, 0, 1), offset=-380.0))
    o, d = rays.pinhole(eye=(0.0, 0.0, 20.0), look_at=(0, 0, 0), fov_deg=10, width=side, height=side)
    return scene, o, d, scene.ray_intervals(o, d)


@pytest.mark.slow
@pytest.mark.parametrize("leaf", ["ellipsoid", "algsphere"])
@pytest.mark.parametrize("method", ["sphere_trace", "hybrid_secant"])
def test_a_leaf_seen_from_outside_its_domain_is_not_stepped_across(backend, method, leaf):
    """256² rays from outside the leaf's domain, over a far floor (:func:`_leaf_above_a_far_floor`):
    the guarantee ray by ray, and 99.9 % of the rays through the leaf CONVERGED on it (stepped at
    φ/L all 16,856 CONVERGED on the floor).  The rest are grazing rays that sphere tracing leaves
    at MAX_ITER (8 of 65,536, numpy; on the leaf alone, at its own φ/L, 460 and 104)."""
    require_method(backend, method)
    scene, o, d, intervals = _leaf_above_a_far_floor(leaf)
    res = _solve(backend, method, scene, o.copy(), d.copy(), 600.0)
    bad = check_guarantee(scene, o, d, res, 600.0, allowance(method, {}), intervals)
    assert not any(bad.values()), {k: (len(v), v[:5]) for k, v in bad.items()}
    assert np.mean(np.isin(res.status, (Status.CONVERGED, Status.MISS))) >= 0.999, np.unique(res.status, return_counts=True)
    on_leaf = np.array([np.size(iv) > 0 and np.ravel(iv)[0] < 100.0 for iv in intervals])
    conv = res.status == Status.CONVERGED
    assert on_leaf.sum() > 16000 and np.mean(conv[on_leaf]) >= 0.999
    assert np.all(res.t[on_leaf & conv] < 21.0)


@pytest.mark.parametrize("leaf", ["ellipsoid", "algsphere"])
def test_a_domain_bound_leaf_is_stepped_within_its_hulls(leaf):
    """In a tree, the leaf's term is L*·max(min(φ/L, −d_outer), d_inner) with the hulls it states
    (:meth:`reference.scene.Field.domain_hulls`: its bounding ball and its domain ball): same sign
    as φ and 1-Lipschitz on 20,000 pairs reaching 50 from the domain, where φ/L's slope is up to
    12 times the bound; beside a half-space z = −3 seen from z = 10 every CONVERGED ray on the
    first crossing (the case that refuted stepping such a leaf at (L*/L)φ alone)."""
    from impls.registry import resolve
    from reference.primitives import Plane

    shape = _domain_leaf(leaf, 0.5)
    scene = Union(Plane(normal=(0, 0, 1), offset=-3.0), shape)
    s = step_field(scene)
    assert s is not scene and s.info.lipschitz == 1.0
    inner, outer = shape.domain_hulls()
    assert inner.radius == 0.5 and outer.radius == 4.0
    rng = np.random.default_rng(7)
    x = rng.normal(size=(20000, 3)) * rng.uniform(0, 30, (20000, 1))
    y = x + rng.normal(size=x.shape) * 10 ** rng.uniform(-6, 1, (x.shape[0], 1))
    assert_sign_and_slope(scene, s, x, y, 1.0)
    dist = np.linalg.norm(x - y, axis=1)
    assert np.max(np.abs(shape.value(x, np) - shape.value(y, np)) / dist) > 10 * shape.info.lipschitz
    o, d = rays.pinhole(eye=(0.0, 0.0, 10.0), look_at=(0, 0, 0), fov_deg=10, width=64, height=64)
    first = np.asarray(scene.first_hit(o, d, 0.0), np.float64)
    for method in ("sphere_trace", "hybrid_secant"):
        res = _solve(resolve("numpy"), method, scene, o.copy(), d.copy(), 30.0)
        conv = res.status == Status.CONVERGED
        assert conv.sum() > 4000 and np.all(np.abs(res.t[conv] - first[conv]) < 1e-6), method


@pytest.mark.parametrize("leaf", ["ellipsoid", "algsphere"])
def test_a_complemented_domain_leaf_is_stepped_within_its_hulls(leaf):
    """The complement of a lone domain-bound leaf has the whole line for ray bounds, so its search
    starts outside the domain (seen from z = 20): stepped at φ/L every ray overshot the leaf and
    was LIPSCHITZ_VIOLATED (4,096 of 4,096, 64², numpy).  Within its hulls every ray is decided,
    on the first crossing: the rays through the leaf CONVERGED at its surface, the others MISS."""
    from impls.registry import resolve

    scene = Complement(_domain_leaf(leaf))
    assert step_field(scene) is not scene and step_field(scene.child) is scene.child
    o, d = rays.pinhole(eye=(0.0, 0.0, 20.0), look_at=(0, 0, 0), fov_deg=10, width=64, height=64)
    intervals = scene.ray_intervals(o, d)
    for method in ("sphere_trace", "hybrid_secant"):
        res = _solve(resolve("numpy"), method, scene, o.copy(), d.copy(), 600.0)
        bad = check_guarantee(scene, o, d, res, 600.0, allowance(method, {}), intervals)
        assert not any(bad.values()), {k: (len(v), v[:5]) for k, v in bad.items()}
        assert np.all(np.isin(res.status, (Status.CONVERGED, Status.MISS))), method
        assert np.sum(res.status == Status.CONVERGED) > 1000, method


@pytest.mark.slow
@pytest.mark.parametrize("method", ["sphere_trace", "hybrid_secant"])
def test_an_ellipsoid_in_a_tight_domain_is_searched_inside_it(backend, method):
    """An ellipsoid with axes (3, 3, 3) and its bound stated on |x| ≤ 3.3: its bounding box's corners
    (5.2 from the centre) lie outside the domain, where φ/L can exceed the distance to it.  Searched
    on the box alone, 1,596 of 16,384 rays (128², numpy) were LIPSCHITZ_VIOLATED; its ray bounds now
    meet the box with the ball |x| ≤ (1 − 10⁻⁵)·3.3 (``Ellipsoid.search_radius``), so at 256² every
    ray keeps the guarantee, none is flagged, and the only undecided rays are grazing rays that
    sphere tracing leaves at MAX_ITER (88 of 65,536, numpy).  The catalog's ellipsoid, whose box
    lies well inside its domain, keeps the box alone."""
    require_method(backend, method)
    assert Ellipsoid((1.0, 0.6, 0.4), domain_radius=6.5).search_radius() is None
    scene = Ellipsoid(axes=(3.0, 3.0, 3.0), domain_radius=3.3)
    assert scene.search_radius() == pytest.approx(3.3 * (1 - 1e-5))
    o, d = rays.pinhole(eye=(10.0, 10.0, 10.0), look_at=(0, 0, 0), fov_deg=25, width=256, height=256)
    intervals = scene.ray_intervals(o, d)
    res = _solve(backend, method, scene, o.copy(), d.copy(), 40.0)
    bad = check_guarantee(scene, o, d, res, 40.0, allowance(method, {}), intervals)
    assert not any(bad.values()), {k: (len(v), v[:5]) for k, v in bad.items()}
    undecided = ~np.isin(res.status, (Status.CONVERGED, Status.MISS))
    assert np.all(res.status[undecided] == Status.MAX_ITER) and undecided.mean() < 0.005, \
        np.unique(res.status, return_counts=True)


def _trees_with_domain_leaves(count: int):
    """The first ``count`` seeds of :func:`tests.test_certified_at_scale.random_scene` whose tree
    holds an ellipsoid or an algebraic sphere among two or more leaves."""
    from tests.test_certified_at_scale import _random_tree

    seeds = []
    for seed in range(200):
        scene = _random_tree(np.random.default_rng(seed), 3)
        leaves = [n for n in scene.walk() if not n.children]
        if len(leaves) > 1 and any(n.info.domain is not None for n in leaves):
            seeds.append(seed)
        if len(seeds) == count:
            return seeds
    raise AssertionError("too few random trees with domain-bound leaves")


@pytest.mark.parametrize("seed", _trees_with_domain_leaves(16))
def test_the_step_field_bounds_domain_leaves_everywhere(seed):
    """Random CSG trees holding ellipsoids and algebraic spheres (:func:`random_scene`), on 20,000
    points reaching 40 from their domains: sign(s) = sign(φ) and s is L*-Lipschitz on 20,000 pairs
    (the sampled slopes below it to rounding), where φ itself is not L-Lipschitz."""
    from tests.test_certified_at_scale import random_scene

    scene = random_scene(seed, 2)[0]
    s = step_field(scene)
    assert s is not scene
    lstar = s.info.lipschitz
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(20000, 3)) * rng.uniform(0, 25, (20000, 1))
    y = x + rng.normal(size=x.shape) * 10 ** rng.uniform(-6, 0.5, (x.shape[0], 1))
    sx, sy = s.value(x, np), s.value(y, np)
    slack = 1e-13 * (np.abs(sx) + np.abs(sy) + lstar * (np.linalg.norm(x, axis=1) + 1)) / np.linalg.norm(x - y, axis=1)
    assert_sign_and_slope(scene, s, x, y, lstar, slack)


def test_a_neural_sdf_local_bound_is_stepped_within_its_boxes():
    """The neural SDF's local bound (L = 1.96 on its certified box B grown by 10⁻³ of the domain's
    diagonal) beside a half-space: the step field's term is bounded by B's and the grown box's
    exact SDFs, same sign as φ and 1-Lipschitz on pairs reaching 20 from the box."""
    from reference.primitives import Plane

    net = get_case("neural.blob.camera.16x16.Llocal").scene
    scene = Union(net, Plane(normal=(0, 0, 1), offset=-5.0))
    s = step_field(scene)
    assert s is not scene and s.info.lipschitz == 1.0
    rng = np.random.default_rng(3)
    x = rng.uniform(-20, 20, (20000, 3)) * rng.uniform(0, 1, (20000, 1))
    y = x + rng.normal(size=x.shape) * 10 ** rng.uniform(-6, 0.5, (x.shape[0], 1))
    assert_sign_and_slope(scene, s, x, y, 1.0)


def test_a_domain_bound_leaf_without_hulls_keeps_the_scene():
    """A user's node whose bound holds on a domain it states in words only (no
    :meth:`~reference.scene.Field.domain_hulls`), or whose hulls call fails: no term bounds them
    beyond the domain, and the tree keeps φ/L."""
    import dataclasses

    class Walled(Sphere):  # a user's subclass: its bound stated on |x| ≤ 2
        @property
        def info(self):
            return dataclasses.replace(super().info, domain="|x| <= 2")

    class Failing(Walled):
        def domain_hulls(self):
            raise RuntimeError("no hulls here")

    for leaf in (Walled(radius=0.5), Failing(radius=0.5)):
        scene = Union(leaf, Box((0.1, 0.5, 0.5)))
        assert step_field(scene) is scene, type(leaf).__name__


def test_a_surface_reaching_past_its_domain_is_refused():
    """The library's domain-bound leaves hold their surface inside their domain, or are refused
    with an error naming ``domain_radius`` (a bound that does not hold on the surface bounds
    nothing there): so their hulls always exist."""
    from reference.implicits import AlgebraicSphere

    for make in (lambda: Ellipsoid(axes=(4.0, 1.0, 1.0)), lambda: AlgebraicSphere(radius=5.0)):
        with pytest.raises(ValueError, match="domain_radius must exceed"):
            make()
    assert Ellipsoid(axes=(4.0, 1.0, 1.0), domain_radius=4.5).domain_hulls() is not None


def test_a_users_domain_bound_leaf_without_hulls_is_flagged_from_outside_its_domain():
    """Over the far floor (:func:`_leaf_above_a_far_floor`), 64² rays: a user's subclass of the
    algebraic sphere that states no hulls keeps φ/L, and the midpoint check a user's node gets
    flags the step across it (LIPSCHITZ_VIOLATED, no CONVERGED ray off the first crossing); a
    :class:`DeclaredLipschitz` over the algebraic sphere passes its child's hulls on and is
    stepped within them (every ray CONVERGED on the first crossing)."""
    from impls.registry import resolve
    from reference.implicits import AlgebraicSphere

    class HullLess(AlgebraicSphere):
        def domain_hulls(self):
            return None

    floor = _leaf_above_a_far_floor("algsphere", 64)[0].children[1]
    o, d = rays.pinhole(eye=(0.0, 0.0, 20.0), look_at=(0, 0, 0), fov_deg=10, width=64, height=64)
    for leaf, rewritten in ((HullLess(radius=1.0), False), (DeclaredLipschitz(AlgebraicSphere(radius=1.0), 8.0), True)):
        scene = Union(leaf, floor)
        assert (step_field(scene) is not scene) == rewritten
        first = np.asarray(scene.first_hit(o, d, 0.0), np.float64)
        for method in ("sphere_trace", "hybrid_secant"):
            res = _solve(resolve("numpy"), method, scene, o.copy(), d.copy(), 600.0)
            conv = res.status == Status.CONVERGED
            assert np.all(np.abs(res.t[conv] - first[conv]) < 1e-6), (type(leaf).__name__, method)
            if rewritten:
                assert conv.all(), method
            else:
                assert np.all(res.status == Status.LIPSCHITZ_VIOLATED), method


def test_a_bound_taken_on_trust_stays_checked():
    """A leaf that declares its bound (:class:`DeclaredLipschitz`) keeps its node in the step field,
    so the root finders still check every step of it (``checks_inside``), against L*."""
    from impls.core.methods_root import checks_inside

    lie = DeclaredLipschitz(Scaled(Sphere(radius=0.3), 4.0), 0.5)
    scene = Union(Sphere(center=(1, 0, 0), radius=0.2), lie)
    s = step_field(scene)
    assert s is not scene and checks_inside(s) and s.info.lipschitz == 0.5
    assert any(n is lie for n in s.walk())


def test_a_leaf_without_a_bound_leaves_the_scene_as_it_is():
    from reference.scene import SceneInfo

    class Unbounded(Sphere):  # a user's subclass stating no bound
        @property
        def info(self):
            return SceneInfo(exact_sdf=False, lipschitz=None, distance_bound=False, smooth=True,
                             exact_hits=True, exact_normals=False, exact_curvature=False,
                             exact_hit_param_grad=False)

    scene = Union(Unbounded(radius=0.5), DeclaredLipschitz(Box((0.1, 0.5, 0.5)), 800.0))
    assert step_field(scene) is scene


def _sphere_beside_a_steep_operand(side: int = 256):
    """A sphere in view and, out of view beside the camera, a box scaled by 3,200 (k·φ, a field as
    steep as an ellipsoid with a 0.05 axis): its bound, 3,200, was the union's, so every step was
    |φ|/3,200."""
    steep = Transform.from_rotvec(Scaled(Box((0.05, 0.3, 0.3)), 3200.0), (0, 0.3, 0), (2.5, 0.0, 2.0))
    scene = Union(Sphere(radius=0.5), steep)
    o, d = rays.pinhole(eye=(0.3, 0.2, 3.0), look_at=(0.3, 0.0, 0.0), fov_deg=45, width=side, height=side)
    return scene, o, d, scene.ray_intervals(o, d)


@pytest.mark.parametrize("method", ["sphere_trace", "hybrid_secant"])
def test_one_steep_operand_no_longer_stalls_the_scene(backend, method):
    """256² rays at the sphere beside the steep operand: every ray decided (CONVERGED or MISS) and
    the guarantee kept ray by ray.  Stepping the union at its largest bound, sphere tracing spent its
    512 steps on each of the 8,580 rays that hit the sphere (86.9 % decided, numpy).  (The hybrid's
    hits crossed so obliquely that φ's sign is rounding over more than its xtol, 1e-12, may be
    UNCERTIFIED: depth_resolved; 6 silhouette rays at slope ~0.03.)"""
    require_method(backend, method)
    scene, o, d, intervals = _sphere_beside_a_steep_operand()
    res = _solve(backend, method, scene, o.copy(), d.copy(), 8.0)
    bad = check_guarantee(scene, o, d, res, 8.0, allowance(method, {}), intervals)
    assert not any(bad.values()), {k: (len(v), v[:5]) for k, v in bad.items()}
    hit = np.array([len(iv) > 0 for iv in intervals])
    exact = np.array([iv[0] if len(iv) else np.inf for iv in intervals])  # (each ray's flat [t0, t1, …])
    sure = depth_resolved(method, scene, o, d, exact, {})
    assert np.all(np.isin(res.status[~hit], (Status.MISS,))), np.unique(res.status, return_counts=True)
    assert np.all(np.isin(res.status[hit & ~sure], (Status.CONVERGED, Status.UNCERTIFIED)))
    assert sure.sum() > 8000 and np.all(res.status[sure] == Status.CONVERGED)


def test_sphere_tracing_the_union_costs_what_the_sphere_alone_costs():
    """The same 256² rays on the sphere alone and on the union beside the steep operand: sphere
    tracing's field evaluations agree to 1 % (1.92 a ray on both, numpy; stepping the union at
    its largest bound it spent 67.2 a ray, and all 512 on each ray that hits)."""
    from impls.registry import resolve

    scene, o, d, _ = _sphere_beside_a_steep_operand()
    numpy_backend = resolve("numpy")
    evals = []
    for field in (scene, scene.children[0]):
        p = numpy_backend.prepare("sphere_trace", field, o.copy(), d.copy(), dtype="float64", t_min=0.0, t_max=8.0)
        evals.append(float(p.result(p.run()).evals.sum()))
    assert evals[0] <= 1.01 * evals[1], evals


def test_the_memo_does_not_keep_scenes_alive():
    """Step fields are remembered per scene object, weakly: a scene no longer used is freed, also
    one that is its own step field (a stored value referring to its key would keep it)."""
    import gc
    import weakref

    for make in (lambda: Sphere(radius=0.5), lambda: Union(Sphere(radius=0.5), Scaled(Box((0.1, 0.5, 0.5)), 2.0))):
        scene = make()
        step_field(scene)
        ref = weakref.ref(scene)
        del scene
        gc.collect()
        assert ref() is None


def _gyroid_ball(x, xp):
    """A gyroid sheet cut to a ball: |∇| ≤ 4√6 (the gyroid's 4·√6 bound at frequency 4)."""
    X, Y, Z = 4.0 * x[..., 0], 4.0 * x[..., 1], 4.0 * x[..., 2]
    g = xp.sin(X) * xp.cos(Y) + xp.sin(Y) * xp.cos(Z) + xp.sin(Z) * xp.cos(X)
    return xp.maximum(xp.abs(g) - 0.3, xp.sqrt(xp.sum(x * x, axis=-1)) - 0.8)


@pytest.mark.parametrize("backend_id", ["numpy", "torch"])
def test_an_understated_user_operand_is_refuted_through_the_step_field(backend_id):
    """A user's gyroid (true slope up to 4√6 ≈ 9.8) declared 3-Lipschitz, in a union with a sphere
    (L = 1): the step field steps the gyroid at φ/3 against L* = 1, where its slope shows above 1 on
    some rays, and then no ray of the call keeps a certificate (CONVERGED or MISS).  Declared at its
    true bound the same union keeps its certificates, with no false hit or certified false miss."""
    from impls.registry import resolve
    from reference.numerical import CallableField, first_hit_numeric

    o, d = rays.pinhole(eye=(0.6, 0.5, 3.5), look_at=(0.6, 0.0, 0.0), up=(0, 1, 0), fov_deg=50, width=64, height=64)
    b = resolve(backend_id)
    for declared, lie in ((3.0, True), (4.0 * np.sqrt(6.0), False)):
        scene = Union(CallableField(_gyroid_ball, lipschitz=declared, name=f"gyroid{declared:g}"),
                      Sphere(center=(1.6, 0.0, 0.0), radius=0.5))
        assert step_field(scene) is not scene
        p = b.prepare("hybrid_secant", scene, o.copy(), d.copy(), dtype="float64", t_min=0.0, t_max=7.0)
        st = p.result(p.run()).status
        certified = np.isin(st, (Status.CONVERGED, Status.MISS))
        if lie:
            assert np.any(st == Status.LIPSCHITZ_VIOLATED) and not certified.any()
        else:
            assert not np.any(st == Status.LIPSCHITZ_VIOLATED) and certified.mean() > 0.99
            ref, err = first_hit_numeric(scene, o, d, 0.0, 7.0)
            t = p.result(p.run()).t
            judged = np.isfinite(err)  # a NaN bound: a tangency the reference could not resolve
            miss, hit = (st == Status.MISS) & judged, (st == Status.CONVERGED) & judged
            assert np.all(np.isinf(ref[miss])), "a certified MISS on a ray that hits"
            ok = np.isfinite(ref[hit]) & (np.abs(t[hit] - ref[hit]) <= allowance("hybrid_secant", {}) + err[hit])
            assert ok.all(), (t[hit][~ok][:5], ref[hit][~ok][:5])


#: :func:`mixed_scene` seeds checked on every backend (those whose rays mostly hit: 23 the most,
#: 46,884 of 65,536).  Before the step field sphere tracing decided 26.8 % of seed 23's rays (436
#: evaluations a ray) and 87.4 % of seed 12's; now 100 % of both (31.4 and 4.7 a ray, numpy)
MIXED_SEEDS = (23, 12, 20, 1)


@pytest.mark.slow
@pytest.mark.parametrize("seed", MIXED_SEEDS)
@pytest.mark.parametrize("method", ["sphere_trace", "hybrid_secant"])
def test_mixed_bound_trees_at_256_squared(backend, method, seed):
    """Random trees whose operands' bounds differ, 256² rays each: the guarantee ray by ray
    (:func:`tests.test_certified_at_scale.check_guarantee`), and at least 99.5 % of the rays decided."""
    if backend.id.startswith(("jax", "torch")) and seed != MIXED_SEEDS[0]:
        pytest.skip("one seed checks this library's arithmetic; numpy checks the algorithm on every seed")
    require_method(backend, method)
    scene, o, d, t_min, intervals = mixed_scene(seed)
    assert step_field(scene) is not scene
    p = backend.prepare(method, scene, o.copy(), d.copy(), dtype="float64", t_min=t_min, t_max=8.0)
    res = p.result(p.run())
    bad = check_guarantee(scene, o, d, res, 8.0, allowance(method, {}), intervals, t_min=t_min)
    assert not any(bad.values()), {k: (len(v), v[:5]) for k, v in bad.items()}
    assert np.mean(np.isin(res.status, (Status.CONVERGED, Status.MISS))) >= 0.995
