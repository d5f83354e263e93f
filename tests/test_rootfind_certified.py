"""CONVERGED means certified, and a declared Lipschitz bound is checked, on every backend.

Reproductions of issue 15's findings 3, 4, 5 and 10 (root finders): a shell whose true slope is
10 declared with L = 1; secant refinement stopping on a small predicted step far from any root;
bisection that cannot stop far from the origin; numpy's finite-difference Newton stalling on a
triple root; BAD_INPUT and unbounded rays.
"""

from __future__ import annotations

import numpy as np
import pytest

from impls import Status
from impls.protocol import Declined
from reference import CallableField, MLPField, Plane, Sphere, catalog, rays
from tests.conformance.common import depth_resolved
from tests.conftest import require_method, resolve_or_skip

ROOT = ("sphere_trace", "hybrid_secant", "march_bisect", "march_secant", "march_newton")


def solve(backend, method, scene, o, d, t_min=0.0, t_max=10.0, **knobs):
    require_method(backend, method)
    prep = backend.prepare(method, scene, o, d, dtype="float64", t_min=t_min, t_max=t_max, **knobs)
    out = prep.run()
    backend.synchronize(out)
    return prep.result(out)


def assert_certified(scene, res, o, d, xtol, t_lo=-np.inf, t_hi=np.inf):
    """Every CONVERGED ray has a sign change of φ within xtol of its depth (or φ = 0 there)."""
    conv = res.status == Status.CONVERGED
    t = res.t[conv]
    assert np.all(np.isfinite(t))
    a, b = np.maximum(t - xtol, t_lo), np.minimum(t + xtol, t_hi)
    fa = scene.value(o[conv] + a[:, None] * d[conv], np)
    fb = scene.value(o[conv] + b[:, None] * d[conv], np)
    ft = scene.value(o[conv] + t[:, None] * d[conv], np)
    ok = (np.sign(fa) != np.sign(fb)) | (ft == 0) | (fa == 0) | (fb == 0)
    assert ok.all(), f"{int((~ok).sum())} CONVERGED rays without a sign change within {xtol:g}: t={t[~ok][:5]}"


def _norm(x, xp):
    return xp.sqrt(xp.sum(x * x, axis=-1))


def shell10(x, xp):
    """10·(||x| − 1| − 0.002): a shell 0.004 thick (thinner than the reference's sample spacing),
    slope 10."""
    return 10.0 * (xp.abs(_norm(x, xp) - 1.0) - 0.002)


def cubed_sphere(x, xp):
    """(|x| − 1)³: the unit sphere as a triple root; slope 3(|x| − 1)² ≤ 12 on |x| ≤ 3."""
    r = _norm(x, xp) - 1.0
    return r * r * r


def inverse_square(x, xp):
    """1 − 1/z²: the plane z = 1 seen from z = 1e-10, where φ ≈ −1e20."""
    return 1.0 - 1.0 / (x[..., 2] * x[..., 2])


@pytest.mark.parametrize("method", ["sphere_trace", "hybrid_secant"])
def test_understated_lipschitz_bound_is_flagged_never_a_silent_miss(backend, method):
    scene = CallableField(shell10, lipschitz=1.0, bounds=((0.0, 0.0, 0.0), 1.5), name="tests.shell10")
    o, d = rays.pinhole(eye=(0.0, 0.0, 3.0), look_at=(0.0, 0.0, 0.0), fov_deg=30.0, width=8, height=8)
    b = np.linalg.norm(np.cross(o, d), axis=1)  # impact parameters: rays with b < 1.05 hit the outer sphere
    hits = b < 1.0019
    assert hits.sum() >= 40
    res = solve(backend, method, scene, o, d, t_max=6.0)
    exact = -np.sum(o * d, axis=1) - np.sqrt(np.maximum(1.002 ** 2 - b ** 2, 0.0))  # first hit of |x| = 1.002
    st = res.status[hits]
    assert not np.any(st == Status.MISS), "an understated L made hits look like misses"
    good = (st == Status.CONVERGED) & (np.abs(res.t[hits] - exact[hits]) <= 1e-6)
    assert np.all(good | (st == Status.LIPSCHITZ_VIOLATED))
    assert np.any(st == Status.LIPSCHITZ_VIOLATED)
    assert np.all(np.isnan(res.t[res.status == Status.LIPSCHITZ_VIOLATED]))


def steep_sphere(x, xp):
    """3·(|x| − 0.7): the sphere of radius 0.7 with slope 3 everywhere."""
    return 3.0 * (_norm(x, xp) - 0.7)


class ThinSlab:
    """A user's own ``Field`` subclass (defined outside ``reference``): a slab 0.01 thick at z = 0
    whose φ is 2× steeper than the L = 1 it states."""

    def __new__(cls):
        from reference.scene import Field, SceneInfo

        class Slab(Field):
            kind = "slab"

            @property
            def info(self):
                return SceneInfo(exact_sdf=False, lipschitz=1.0, distance_bound=False, smooth=True,
                                 exact_hits=False, exact_normals=False, exact_curvature=False,
                                 exact_hit_param_grad=False)

            def _eval(self, x, xp, cursor):
                return 2.0 * (xp.abs(x[..., 2]) - 0.005)

        return Slab()


@pytest.mark.parametrize("method", ["sphere_trace", "hybrid_secant"])
@pytest.mark.parametrize("lie", ["steep_sphere", "thin_slab"])
def test_a_step_that_jumps_everything_under_an_understated_bound_is_flagged(backend, method, lie):
    """A declared bound is checked inside every step, not only at its ends.  From 2.8 units away a
    field 3× steeper than its declared L = 1 (no bounding ball given) makes the first step jump the
    whole ray, and both of its ends agree with L: the old code certified every ray a MISS.  A
    user's ``Field`` subclass is a declaration too (a slab 0.01 thick, 2× steeper than stated,
    which the ray crosses obliquely).  Every ray whose first crossing exists now ends
    LIPSCHITZ_VIOLATED or at that crossing, never MISS; and the check costs nothing on the
    library's own scenes, whose bounds their construction proves."""
    from impls.core.methods_root import checks_inside

    if lie == "steep_sphere":
        scene = CallableField(steep_sphere, lipschitz=1.0, name="tests.steep_sphere")
        o, d = rays.pinhole(eye=(0.3, 0.9, 2.6), look_at=(0.0, 0.0, 0.0), fov_deg=45.0, width=16, height=16)
        b = np.linalg.norm(np.cross(o, d), axis=1)
        hits = b < 0.7
        exact = np.where(hits, -np.sum(o * d, axis=1) - np.sqrt(np.maximum(0.49 - b ** 2, 0.0)), np.inf)
    else:
        scene = ThinSlab()
        o, d = rays.pinhole(eye=(0.4, 0.2, 2.5), look_at=(1.5, 0.0, 0.0), fov_deg=40.0, width=16, height=16)
        hits = d[:, 2] < 0
        exact = np.where(hits, (o[:, 2] - 0.005) / np.maximum(-d[:, 2], 1e-300), np.inf)
        hits &= exact <= 6.0
    assert checks_inside(scene) and hits.sum() >= 40
    res = solve(backend, method, scene, o, d, t_max=6.0)
    st = res.status[hits]
    assert not np.any(st == Status.MISS), f"{int(np.sum(st == Status.MISS))} hits certified as misses"
    good = (st == Status.CONVERGED) & (np.abs(res.t[hits] - exact[hits]) <= 1e-6)
    assert np.all(good | (st == Status.LIPSCHITZ_VIOLATED)), res.status_counts()
    assert np.any(st == Status.LIPSCHITZ_VIOLATED)


def test_only_bounds_taken_on_trust_are_checked_inside_every_step():
    """The midpoint check costs an evaluation per step: it runs where a node's bound is a
    declaration (a user's field, a ``Field`` subclass of the user's, the catalog's deliberately
    understated cases), not on the library's scenes, whose bounds their construction proves."""
    from impls.core.methods_root import checks_inside
    from reference.cases import DeclaredLipschitz

    assert checks_inside(CallableField(steep_sphere, lipschitz=1.0)) and checks_inside(ThinSlab())
    assert checks_inside(DeclaredLipschitz(Sphere(radius=1.0), 0.5))
    assert not any(checks_inside(case.scene) for case in catalog("torus.camera.32x32") + catalog("csg.union.camera.32x32"))


def test_the_numerical_reference_flags_an_understated_bound():
    from reference import first_hit_numeric

    scene = CallableField(shell10, lipschitz=1.0, bounds=((0.0, 0.0, 0.0), 1.5), name="tests.shell10")
    o, d = rays.pinhole(eye=(0.0, 0.0, 3.0), look_at=(0.0, 0.0, 0.0), fov_deg=30.0, width=8, height=8)
    b = np.linalg.norm(np.cross(o, d), axis=1)
    t, err = first_hit_numeric(scene, o, d, 0.0, 6.0)
    hits = b < 1.0019
    exact = -np.sum(o * d, axis=1) - np.sqrt(np.maximum(1.002 ** 2 - b ** 2, 0.0))
    certified_miss = hits & np.isinf(t) & np.isfinite(err)
    assert not certified_miss.any(), f"{int(certified_miss.sum())} hits certified as misses"
    flagged = np.isnan(t)
    assert np.all(np.isinf(err[flagged]))
    assert np.all(flagged[hits] | (np.abs(t[hits] - exact[hits]) <= 1e-9))


@pytest.mark.parametrize("method, knobs", [("march_secant", {"step": 1e8}), ("hybrid_secant", {})])
def test_secant_converges_only_on_a_certified_bracket(backend, method, knobs):
    scene = CallableField(inverse_square, lipschitz=None if method != "hybrid_secant" else 2e30, name="tests.invsq")
    o = np.array([[0.0, 0.0, 1e-10]] * 4)
    d = np.array([[0.0, 0.0, 1.0]] * 4)
    res = solve(backend, method, scene, o, d, t_max=1e10, **knobs)
    conv = res.status == Status.CONVERGED
    assert np.all(np.abs(res.t[conv] - (1.0 - 1e-10)) <= 1e-9), res.t
    assert_certified(scene, res, o, d, 1e-9)


@pytest.mark.parametrize("method", ["hybrid_secant", "march_secant", "march_newton", "march_bisect"])
def test_triple_root_converges_certified(backend, method):
    n = 20_000 if backend.id == "numpy" else 2_000
    s = np.linspace(0.0, 0.01, n, endpoint=False)
    o = np.stack([np.zeros(n), np.zeros(n), -3.0 - s], axis=1)
    d = np.tile([0.0, 0.0, 1.0], (n, 1))
    scene = CallableField(cubed_sphere, lipschitz=12.0, bounds=((0.0, 0.0, 0.0), 1.0 + 1e-6), name="tests.cubed")
    res = solve(backend, method, scene, o, d, t_max=6.0)
    conv = res.status == Status.CONVERGED
    assert conv.mean() >= 0.999, {Status(int(k)).name: int(v) for k, v in zip(*np.unique(res.status, return_counts=True))}
    # a triple root: |φ| ≤ eps·|x|³ within ~eps^(1/3) of it, so the sign is only known to ~1e-5
    xtol = 2e-5
    assert np.max(np.abs(res.t[conv] - (2.0 + s[conv]))) <= xtol
    assert np.max(res.evals) < 1000  # numpy's Newton stalled at 12,291 evaluations (MAX_ITER) before


@pytest.mark.parametrize("distance", [1e4, 1e6])
def test_bisection_stops_at_adjacent_floats_far_away(backend, distance):
    o = np.array([[0.0, 0.0, distance]] * 8)
    d = np.tile([0.0, 0.0, -1.0], (8, 1))
    # (an xtol below the float spacing there, 1.8e-12 at 1e4: the default 1e-10 is not, since the
    # marches certify their brackets against φ's rounding)
    res = solve(backend, "march_bisect", Sphere(), o, d, t_max=2 * distance, xtol=1e-13)
    assert np.all(res.status == Status.CONVERGED)
    assert np.all(np.abs(res.t - (distance - 1.0)) <= 4 * np.spacing(distance))
    assert np.max(res.evals) < 200


@pytest.mark.parametrize("method", ROOT)
def test_bad_input_rays_get_nan_depth(backend, method):
    o = np.array([[0.0, 0.0, 3.0], [np.nan, 0.0, 3.0], [0.0, np.inf, 3.0]])
    d = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0], [0.0, 0.0, -1.0]])
    res = solve(backend, method, Sphere(), o, d)
    assert res.status[0] == Status.CONVERGED
    assert np.all(res.status[1:] == Status.BAD_INPUT)
    assert np.all(np.isnan(res.t[1:]))


@pytest.mark.parametrize("method", ["sphere_trace", "hybrid_secant"])
def test_a_ray_with_no_surface_and_no_bound_is_a_miss(backend, method):
    o = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 2.0]])
    d = np.array([[0.0, 0.0, 1.0], [0.0, 0.6, 0.8]])
    res = solve(backend, method, Plane(), o, d, t_max=np.inf, max_steps=100_000)
    assert np.all(res.status == Status.MISS), res.status
    assert np.all(np.isinf(res.t))


@pytest.mark.slow  # compiles many kernels or sweeps a whole catalog
@pytest.mark.parametrize("method", ROOT)
def test_no_false_lipschitz_flag_anywhere_in_the_catalog(method):
    """No correct scene of the catalog is flagged; the cases whose declared bound is a planted
    lie (family ``understated``) end flagged or at the exact hit, never a miss."""
    from reference.cases import adversarial_family

    numpy_backend = resolve_or_skip("numpy")
    flagged, lies = {}, 0
    for case in catalog():
        if case.scene.info.lipschitz is None and method in ("sphere_trace", "hybrid_secant"):
            continue
        res = solve(numpy_backend, method, case.scene, case.origins, case.directions, case.t_min, case.t_max)
        lipv = res.status == Status.LIPSCHITZ_VIOLATED
        if adversarial_family(case.tags) == "understated":
            lies += 1
            exact = case.exact_t
            right = (res.status == Status.CONVERGED) & (np.abs(res.t - exact) <= 1e-6)
            assert np.all(lipv | right), (case.id, res.status_counts())
            continue
        if lipv.any():
            flagged[case.id] = int(lipv.sum())
    assert not flagged
    assert lies >= 1


@pytest.mark.parametrize("method", ["march_secant", "march_bisect", "march_newton"])
def test_constant_step_marching_checks_a_declared_bound(backend, method):
    """Constant-step marching does not step by L, but it evaluates both ends of every step: where
    the scene declares L it checks it too, so a false L is flagged rather than trusted (a shell
    thinner than the step would otherwise be a silent miss)."""
    scene = CallableField(shell10, lipschitz=1.0, bounds=((0.0, 0.0, 0.0), 1.5), name="tests.shell10")
    o, d = rays.pinhole(eye=(0.0, 0.0, 3.0), look_at=(0.0, 0.0, 0.0), fov_deg=30.0, width=8, height=8)
    b = np.linalg.norm(np.cross(o, d), axis=1)
    hits = b < 1.0019
    res = solve(backend, method, scene, o, d, t_max=6.0)
    exact = -np.sum(o * d, axis=1) - np.sqrt(np.maximum(1.002 ** 2 - b ** 2, 0.0))
    st = res.status[hits]
    assert not np.any(st == Status.MISS), "an understated L made hits look like misses"
    good = (st == Status.CONVERGED) & (np.abs(res.t[hits] - exact[hits]) <= 1e-6)
    assert np.all(good | (st == Status.LIPSCHITZ_VIOLATED))
    assert np.any(st == Status.LIPSCHITZ_VIOLATED)
    # the same field with no declared bound: nothing to check, marching's documented limit (a miss)
    plain = CallableField(shell10, lipschitz=None, bounds=((0.0, 0.0, 0.0), 1.5), name="tests.shell10.plain")
    assert not np.any(solve(backend, method, plain, o, d, t_max=6.0).status == Status.LIPSCHITZ_VIOLATED)


def _far_spheres():
    """Exact SDFs far from the origin, seen from 3 units: φ carries rounding of ε·|x| (1e6, 1e9)
    while |φ| and t are a few units, so a slack relative to |φ| and |t| alone flags them."""
    rng = np.random.default_rng(1)
    for c, r in ((1e6, 1e6), (1e9, 1.0), (0.0, 1e9)):
        centre = np.array([c, 0.5 * c, 0.0 if c else 1e9 + 4.0])
        eye = centre - np.array([0.0, 0.0, r + 3.0])
        n = 64
        tgt = centre + np.c_[rng.uniform(-0.3, 0.3, (n, 2)) * r, np.zeros(n)]
        d = tgt - eye
        d /= np.linalg.norm(d, axis=1)[:, None]
        yield Sphere(center=tuple(centre), radius=r), np.tile(eye, (n, 1)), d, 2 * r + 10.0


@pytest.mark.parametrize("method", ROOT)
def test_no_false_lipschitz_flag_far_from_the_origin(backend, method):
    for scene, o, d, t_max in _far_spheres():
        res = solve(backend, method, scene, o, d, t_max=t_max)
        assert not np.any(res.status == Status.LIPSCHITZ_VIOLATED), (scene.spec(), res.status_counts())


def test_the_numerical_reference_does_not_flag_far_spheres():
    from reference import first_hit_numeric

    for scene, o, d, t_max in _far_spheres():
        t, err = first_hit_numeric(scene, o, d, 0.0, t_max)
        assert np.all(np.isfinite(err)), scene.spec()


def _certification_scenes():
    """(scene, o, d, t_max): a camera on the unit sphere, the torus ∪ box camera case with rays
    grazing the torus, the MLP camera case, and the triple root."""
    from reference.cases import get_case

    o, d = rays.pinhole(eye=(0.0, 0.0, 3.0), look_at=(0.0, 0.0, 0.0), fov_deg=40.0, width=16, height=16)
    yield Sphere(), o, d, 10.0
    for cid in ("csg.union.camera.32x32", "mlp.camera.32x32"):
        case = get_case(cid)
        yield case.scene, case.origins, case.directions, case.t_max
    n = 256
    s = np.linspace(0.0, 0.01, n, endpoint=False)
    yield (CallableField(cubed_sphere, lipschitz=12.0, bounds=((0.0, 0.0, 0.0), 1.0 + 1e-6), name="tests.cubed"),
           np.stack([np.zeros(n), np.zeros(n), -3.0 - s], axis=1), np.tile([0.0, 0.0, 1.0], (n, 1)), 6.0)


@pytest.mark.parametrize("xtol", [1e-4, 1e-12])
@pytest.mark.parametrize("method", ["hybrid_secant", "march_bisect", "march_secant", "march_newton"])
def test_every_converged_ray_lies_in_a_certified_bracket(backend, method, xtol):
    """The conformance check of CONVERGED (:func:`assert_certified`) over scenes, methods, backends
    and tolerances: a loose xtol is where a verdict on a short predicted step would show.

    The MLP's declared bound (a product of spectral norms) is loose: a constant-step march's
    samples have |φ|/L far below its step, their spheres cover no step, and it certifies no
    crossing past its first step (``ConstantStep``: the frontier stays at the start).  There its
    hits are UNCERTIFIED, none CONVERGED; the hybrid, stepping by |φ|/L, certifies them."""
    checked = 0
    for scene, o, d, t_max in _certification_scenes():
        if scene.info.lipschitz is None and method == "hybrid_secant":
            continue
        try:
            res = solve(backend, method, scene, o, d, t_max=t_max, xtol=xtol)
        except Declined:  # a compiling backend (numba) and a field it does not compile: the others still count
            continue
        checked += 1
        if method.startswith("march") and isinstance(scene, MLPField):
            assert not np.any(res.status == Status.CONVERGED)
            assert np.mean(res.status == Status.UNCERTIFIED) > 0.2
            continue
        assert np.mean(res.status == Status.CONVERGED) > 0.2
        # the float spacing of t bounds what a bracket can certify (adjacent floats)
        assert_certified(scene, res, o, d, max(xtol, 4 * np.spacing(t_max)))
    assert checked, "the backend declined every scene"


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_a_plain_step_rejected_by_rounding_is_not_repeated(dtype):
    """The hybrid's plain step r = |φ|/L is rejected when its end lands within φ's rounding of a
    surface it does not cross (certified radii rc + rc_n < r); the next step is then
    max(rc, min_step), which stands (here rc = 1, a certified step).  Before, the ray repeated the same rejected step to ``max_steps`` (25–42
    float32 rays of 256 on the mesh cases, each 4,096 steps).  φ = |x + 1| + 16ε along a ray from
    x = −2: the plain step from t = 0 ends at t = 1 + 16ε, where φ = 32ε lies between one and two
    resolutions (8ε(|t| + |o|₁)) and is rejected; no surface, and φ's floor is below rounding at
    t = 1, so the honest answer is UNCERTIFIED there, within a few steps."""
    from impls.core.rootfind import CertifiedStep, MarchRefine, Secant

    floor = 16 * float(np.finfo(dtype).eps)

    def ev(o, d, t, deriv):
        return (np.abs(o[:, 0] + t * d[:, 0] + 1.0) + dtype(floor)).astype(dtype), None, 1

    alg = MarchRefine(rule=CertifiedStep(inv_lip=1.0, min_step=1e-4, overstep=1e-4), refiner=Secant(), xtol=1e-12,
                      max_steps=64, t_min=0.0, t_max=3.0, resolve=True)
    o, d = np.array([[-2.0, 0.0, 0.0]], dtype), np.array([[1.0, 0.0, 0.0]], dtype)
    s = alg.init(np, o, d, ev)
    steps = 0
    while s["status"][0] == Status.IN_PROGRESS and steps < 64:
        s = alg.step_march(np, s, o, d, ev)
        steps += 1
    assert s["status"][0] == Status.UNCERTIFIED and steps < 10, (Status(int(s["status"][0])).name, steps, s["t"])
    assert s["t"][0] == 1.0


@pytest.mark.parametrize("case_id", ["mesh.fin.thin", "mesh.fin.grazing.1e-6"])
def test_no_float32_hybrid_ray_spins_to_max_steps_on_the_mesh_fin(backend, case_id):
    """The rays of the stability plan's mesh cases that repeated a rejected plain step to
    ``max_steps`` in float32 (25 and 37 of 256 on every backend) end within a few dozen
    evaluations, none of them MAX_ITER, none CONVERGED off a certified bracket."""
    require_method(backend, "hybrid_secant")
    case = catalog(case_id)[0]
    if "float32" not in backend.capabilities.dtypes:
        pytest.skip(f"{backend.id} has no float32")
    prep = backend.prepare("hybrid_secant", case.scene, case.origins, case.directions, dtype="float32",
                           t_min=case.t_min, t_max=case.t_max)
    out = prep.run()
    backend.synchronize(out)
    res = prep.result(out)
    assert not np.any(res.status == Status.MAX_ITER), res.status_counts()
    assert res.evals.max() < 200, res.evals.max()


@pytest.mark.slow  # a 1024² camera of the fin mesh: ~2 s a backend, the mesh's host queries
@pytest.mark.parametrize("backend_id", ["numpy", "torch:cpu"])
def test_float32_hybrid_ends_every_ray_of_a_1024_squared_fin_camera(backend_id):
    """At the ray counts users render, in float32, on the thin-walled mesh: the hybrid ends every
    ray without spinning to ``max_steps`` (before: 124,344 of 1,048,576 rays MAX_ITER, 139 s on
    numpy; a ray repeating a rejected plain step, or creeping along the wall by certified radii
    shorter than ``min_step``), with no false hit and no certified MISS on a ray trimesh's
    independent intersector hits (a subsample of every 64th ray: trimesh is slow on a million)."""
    from reference.mesh_cases import _cam, stored_mesh
    from tests.test_mesh_trimesh_crosscheck import trimesh_first_hits

    backend = resolve_or_skip(backend_id)
    mesh = stored_mesh("fin")
    o, d = _cam(1024, eye=(1.6, -1.9, 1.5))
    prep = backend.prepare("hybrid_secant", mesh, o, d, dtype="float32", t_min=0.0, t_max=10.0)
    out = prep.run()
    backend.synchronize(out)
    res = prep.result(out)
    assert not np.any(res.status == Status.MAX_ITER), res.status_counts()
    sub = np.arange(0, o.shape[0], 64)
    ref = trimesh_first_hits(mesh, o[sub], d[sub], 0.0, 10.0)
    st = res.status[sub]
    assert np.isfinite(ref).sum() > 1000
    assert not np.any((st == Status.CONVERGED) & ~np.isfinite(ref))
    assert not np.any((st == Status.MISS) & np.isfinite(ref))


def test_an_exact_zero_closes_the_bracket_at_itself_and_is_certified_as_first_from_there():
    """Refinement that lands on φ = 0 exactly closes the bracket at that point, [c, c], and the
    certification stage must then cover the stretch up to c.  The bracket's far end used to stay
    where it was (here a = 1, before a thin slab), and certification, which covers the stretch up
    to the bracket's start, called c the first crossing with the slab [1.995, 2.005] unseen: a
    later crossing CONVERGED (found at 256² rays on all five array backends, a thin shell grazed
    before a wall).  φ(t) = min(|t − 2| − 0.005, 2.25 − t) along x; the state is that of a
    secant refinement of [1, 2.375] whose last two iterates, 2.5 and 2.375, put its next one at
    2.25 exactly (dyadic arithmetic), where φ = 0; the march's frontier ends at the slab."""
    from impls.core.rootfind import CertifiedStep, MarchRefine, Secant

    def ev(o, d, t, deriv):
        x = o[:, 0] + t * d[:, 0]
        return np.minimum(np.abs(x - 2.0) - 0.005, 2.25 - x), None, 1

    alg = MarchRefine(rule=CertifiedStep(inv_lip=1.0, min_step=1e-4, overstep=1e-4), refiner=Secant(), xtol=1e-12,
                      max_steps=256, t_min=0.0, t_max=3.0, resolve=True)
    o, d = np.array([[0.0, 0.0, 0.0]]), np.array([[1.0, 0.0, 0.0]])
    s = alg.init(np, o, d, ev)
    one = np.ones(1)
    s.update(t=2.375 * one, f=-0.125 * one, p=2.5 * one, fp=-0.25 * one, a=1.0 * one, fa=0.995 * one,
             b=2.375 * one, wq=np.inf * one, u=1.995 * one, cp=1.0 * one, fcp=0.995 * one,
             # the certified bracket: between the spheres of a (radius 0.995) and of 2.375 (0.125)
             A=1.995 * one, B=2.25 * one,
             iterations=np.ones(1, np.int32), phase=np.full(1, alg.stages.index("step_refine"), np.int32))
    s = alg.step_refine(np, s, o, d, ev)
    assert s["t"][0] == 2.25 and s["a"][0] == s["b"][0] == 2.25  # closed at the exact zero, [c, c]
    steps = 0
    while s["status"][0] == Status.IN_PROGRESS and steps < 256:
        s = getattr(alg, alg.stages[int(s["phase"][0])])(np, s, o, d, ev)
        steps += 1
    status, t = Status(int(s["status"][0])), float(s["t"][0])
    # the first crossing, or no claim: never the wall behind the slab
    assert status in (Status.CONVERGED, Status.UNCERTIFIED), (status.name, t)
    if status == Status.CONVERGED:
        assert abs(t - 1.995) <= 1e-9, t


def test_float32_hybrid_certifies_an_oblique_floor(backend):
    """Over-relaxed steps aim at the overlap of the *certified* spheres (radii less φ's rounding),
    which is what a step is judged by.  Aimed at the plain radii, the over-relaxation's 10 % margin
    fell below float32's rounding slack near a surface seen obliquely: every second step was
    rejected, the crossing step never came, and the forced step of ``min_step`` stood uncertified
    before the crossing, so 1,234 of this floor's 3,008 float32 hits (41 %) were UNCERTIFIED
    (numpy; float64: none).  Now 274; every CONVERGED ray is on the exact hit to float32's
    resolution, and float64 is unchanged (every hit CONVERGED, numpy).  In float32 the tolerance
    asked is 1e-4, above φ's rounding there: at the default 1e-12 the closing width is 4·rounding
    (MarchRefine.closing_width), which brackets of resolved signs reach only at slopes above about
    0.5, so the floor's hits at 18–30° are UNCERTIFIED (61 %), as sphere tracing's are; every hit
    the dtype resolves to that width (depth_resolved) is CONVERGED there."""
    require_method(backend, "hybrid_secant")
    if "float32" not in backend.capabilities.dtypes:
        pytest.skip(f"{backend.id} runs no float32")
    scene = Plane((0.0, 1.0, 0.0), -1.0)  # the floor y = −1, seen from (0, 0, 3) at 18–45°
    o, d = rays.pinhole(eye=(0.0, 0.0, 3.0), look_at=(0.0, -1.0, 0.0), fov_deg=50, width=64, height=64)
    exact = scene.first_hit(o, d, 0.0)
    hits = np.isfinite(exact) & (exact <= 10.0)
    # (float64 on numpy only: a compiling backend would pay a second kernel for what the float64
    # tests of the certified methods already hold on every backend)
    runs = [("float32", 1e-4), ("float32", None)] + ([("float64", None)] if backend.id == "numpy" else [])
    for dtype, xtol in runs:
        try:
            prep = backend.prepare("hybrid_secant", scene, o.copy(), d.copy(), dtype=dtype, t_min=0.0, t_max=10.0,
                                   **({} if xtol is None else {"xtol": xtol}))
        except Declined as e:
            pytest.skip(str(e))
        res = prep.result(prep.run())
        conv = res.status == Status.CONVERGED
        tol = float(np.sqrt(np.finfo(dtype).eps)) if dtype == "float32" else 1e-9
        assert np.all(np.abs(res.t[conv] - exact[conv]) <= tol * np.maximum(1.0, exact[conv]))
        assert not np.any((res.status == Status.MISS) & hits)
        flagged = np.mean(res.status[hits] == Status.UNCERTIFIED)
        if xtol is None and dtype == "float32":
            must = depth_resolved("hybrid_secant", scene, o, d, exact, {}, dtype=dtype)
            assert must.sum() >= 50 and np.all(conv[must]), (dtype, must.sum(), flagged)
        else:
            assert flagged <= (0.15 if dtype == "float32" else 0.0), (dtype, flagged)


def _scaled_floor_rays(n=256):
    """Rays from 0.005–0.08 above the floor z = 0 at 18.5–24.5° from its normal: they approach it
    at a slope of 0.91–0.95 of L, where the hybrid's crossing step 1.05·r neither reaches the floor
    nor stands certified (r + r_n < 1.05·r)."""
    rng = np.random.default_rng(0)
    th = np.deg2rad(rng.uniform(18.5, 24.5, n))
    ph = rng.uniform(0.0, 2.0 * np.pi, n)
    d = np.column_stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), -np.cos(th)])
    o = np.column_stack([rng.uniform(-1.0, 1.0, (n, 2)), rng.uniform(0.005, 0.08, n)])
    return o, d


def test_the_certified_step_takes_no_crossing_step_without_a_last_step():
    """The rule's step size at the start (p = t) is the certified march's, not the crossing step,
    however the difference |φ_p|/L − |φ|/L rounds: here φ_p is φ one ulp up, as a fused
    multiply-add leaves it (the numerator a rounding error, the denominator 0)."""
    from impls.core.rootfind import CertifiedStep

    rule = CertifiedStep(inv_lip=1.0 / 0.37, min_step=1e-4, overstep=1e-4, extrapolate=1.05, reach=0.1)
    t = np.array([1.0, 1.0])
    f = np.array([0.01, 0.01])
    s = {**rule.init(np, t), "p": t.copy(), "fp": np.array([np.nextafter(0.01, 1.0), np.nextafter(0.01, 0.0)])}
    r, h = rule.size(np, s, t, f, rc=rule.radius(np, f))
    np.testing.assert_array_equal(r, rule.radius(np, f))
    assert np.all(h <= r), (h, r)  # the plain certified step (over-relaxation needs a slope)


def test_a_refinement_step_below_the_float_spacing_is_lifted_past_it():
    """Near a root secant and Newton close in from one side, so a step shorter than xtol/2 is
    lengthened beyond the predicted root (Brent's "step at least tol").  With xtol = 1e-12 below
    float32's spacing at t (3.7e-9 at t ≈ 0.04) that lift rounded to t itself: the same point was
    evaluated again, and only the safeguard's bisections closed the bracket (jax, float32, the
    scaled floor below: 43 evaluations a ray).  The lift is at least two float spacings of t."""
    from impls.core.rootfind import Secant

    t = np.array([0.0392969], np.float32)
    s = {"p": t - np.float32(1e-3), "fp": np.array([1e-3], np.float32), "wq": np.array([1.0], np.float32)}
    f = np.array([-2.5e-11], np.float32)  # the secant's zero is 2.5e-11 before t: t itself in float32
    a, b = t - np.float32(6e-5), t.copy()
    c = Secant().propose(np, s, t, f, a, b, 0.5 * (a + b), np.array([False]), 1e-12)
    assert c.dtype == np.float32 and a[0] <= c[0] < t[0], (c, t)


@pytest.mark.parametrize("k, dtype", [(0.37, "float64"), (3.3, "float64"), (0.37, "float32")])
def test_the_hybrid_brackets_a_scaled_floor_in_a_few_evaluations(backend, k, dtype):
    """A floor scaled to L = k ≠ 1, approached at a slope of 0.91–0.95 of L (``_scaled_floor_rays``):
    every ray CONVERGED on the exact hit within a few evaluations, on every backend and dtype.

    Two faults of jax's compiled arithmetic showed here.  With no last step (the start, or after a
    rejection: p = t) the approach slope σ came out NaN from 0/0 only while |φ_p|/L − |φ|/L rounded
    to exactly 0; XLA contracts it into a fused multiply-add whose numerator is the product's
    rounding error, so σ = 1 on about half the rays, a crossing step of 1.05·r that is rejected
    and taken again from the same point until ``max_steps`` (jax: 128 and 120 of these 256 rays
    MAX_ITER at 4,096 steps in float64, 150 in float32).  And in float32 the refiners' lift of
    xtol/4 rounded to t itself (43 evaluations a ray; the rays' φ lands 2.5e-11 off zero there)."""
    from reference import Scaled

    require_method(backend, "hybrid_secant")
    if dtype not in backend.capabilities.dtypes:
        pytest.skip(f"{backend.id} runs no {dtype}")
    scene = Scaled(Plane((0.0, 0.0, 1.0), 0.0), k)
    o, d = _scaled_floor_rays()
    prep = backend.prepare("hybrid_secant", scene, o, d, dtype=dtype, t_min=0.0, t_max=10.0)
    out = prep.run()
    backend.synchronize(out)
    res = prep.result(out)
    exact = o[:, 2] / -d[:, 2]
    tol = float(np.sqrt(np.finfo(dtype).eps)) if dtype == "float32" else 1e-9
    assert (res.status == Status.CONVERGED).all(), np.unique(res.status, return_counts=True)
    assert np.all(np.abs(res.t - exact) <= tol)
    assert res.evals.max() <= 16, (res.evals.max(), res.evals.mean())


def test_a_certification_sample_checks_the_bound_between_its_ends():
    """The certification stage extends the frontier with samples stepped from the last certified
    one, cp, on the strength of L, as the march does: its two ends check the bound the same way.
    Here a plane crossed at slope 3 declared with L = 1, a row in certification mode at cp = 0
    (φ = 6) whose sample lands at the bracket's start a = 1.99 (φ = 0.03): the slope between them
    is 3, LIPSCHITZ_VIOLATED (before, the sample was taken on trust)."""
    from impls.core.methods_root import build_hybrid
    from impls.methods import get_method

    scene = CallableField(lambda x, xp: 3.0 * (x[..., 2] - 1.0), lipschitz=1.0, name="tests.steep_plane")
    knobs = get_method("hybrid_secant").validate({})
    alg = build_hybrid(scene, 0.0, 10.0, knobs, ladder=0)
    o, d = np.array([[0.0, 0.0, 3.0]]), np.array([[0.0, 0.0, -1.0]])
    ev = resolve_or_skip("numpy").ray_eval(scene)
    s = alg.init(np, o, d, ev)
    one = np.ones(1)
    s.update(t=2.0 * one, f=0.0 * one, p=1.99 * one, fp=0.03 * one, a=1.99 * one, fa=0.03 * one, b=2.0 * one,
             u=0.0 * one, cp=0.0 * one, fcp=6.0 * one, kap=one, cm=np.array([True]), phase=np.array([2], np.int32))
    out = alg.step_certify(np, s, o, d, ev)
    assert out["status"][0] == Status.LIPSCHITZ_VIOLATED, Status(int(out["status"][0]))
