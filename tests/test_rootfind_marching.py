"""The marching stage's accelerations (impls.core.rootfind.MarchRefine): ladder steps for rays
still marching after ``ladder_after`` steps, and the hybrid's over-relaxed steps and crossing step
(``extrapolate``, ``reach``).  They change how many loop iterations a ray takes and, for the
hybrid, how many rays end UNCERTIFIED, never which crossing a CONVERGED ray reports."""

from __future__ import annotations

import numpy as np
import pytest

from impls import Status, registry
from reference import Box, Sphere
from reference.cases import get_case
from tests.conformance.common import depth_resolved


def _run(method, scene, o, d, backend="numpy", **knobs):
    b = registry.resolve(backend)
    prep = b.prepare(method, scene, o, d, dtype="float64", t_min=0.0, t_max=10.0, **knobs)
    return prep.result(prep.run())


def _grazing_sphere_rays(deltas):
    """Rays along +x at height 1 + δ above the unit sphere's centre (δ < 0: a hit δ deep)."""
    o = np.zeros((len(deltas), 3))
    o[:, 0], o[:, 1] = -3.0, 1.0 + np.asarray(deltas)
    d = np.tile([1.0, 0.0, 0.0], (len(deltas), 1))
    return o, d


def _torus_box_camera_and_grazing_rays():
    """The torus ∪ box camera case's scene and rays, plus rays grazing the torus's outer equator
    at x = 0 (3e-7 and 1e-5 outside it, 1e-5 and 1e-3 inside)."""
    case = get_case("csg.union.camera.32x32")
    og, dg = _grazing_sphere_rays([3e-7, 1e-5, -1e-5, -1e-3])
    og[:, 1] *= 1.25
    return case.scene, np.concatenate([case.origins, og]), np.concatenate([case.directions, dg])


def _march_cases():
    """(backend, method) of the march certification tests: every march on the array backends; on
    the compiling ones (numba, jax: a kernel per refiner, 3–11 s cold each) march_secant only, as
    the march's verdicts are one code for every refiner (numba's template, the core's steps)."""
    return ([(b, m) for b in ("numpy", "torch:cpu", "warp") for m in ("march_secant", "march_bisect", "march_newton")]
            + [("numba", "march_secant"), pytest.param("jax:cpu", "march_secant", marks=pytest.mark.slow)])


def _exact_or_inf(scene, o, d):
    t = scene.first_hit(o, d, 0.0)
    return np.where(t <= 10.0, t, np.inf)


@pytest.mark.parametrize("backend", ["numpy", "torch"])
@pytest.mark.parametrize("method", ["hybrid_secant", "march_secant", "march_bisect"])
def test_ladder_and_extrapolation_find_the_same_hits(backend, method):
    if backend == "torch":
        pytest.importorskip("torch")
    scene, o, d = _torus_box_camera_and_grazing_rays()
    hybrid = method == "hybrid_secant"
    plain = _run(method, scene, o, d, backend, xtol=1e-12, ladder=0, **({"extrapolate": 0.0} if hybrid else {}))
    fast = _run(method, scene, o, d, backend, xtol=1e-12, ladder_after=4)
    assert (fast.evals > fast.iterations + 1).any()  # ladder steps were taken (samples past a stop)
    if not hybrid:
        # the same steps, taken 16 at a time: each pair judged counts against max_steps as a step
        # (a refinement may end a step apart: the samples t + jΔ and the running sum differ in the last bit)
        assert np.abs(fast.iterations - plain.iterations).max() <= 1
        assert np.mean(fast.iterations == plain.iterations) > 0.99
        np.testing.assert_array_equal(fast.status, plain.status)
        conv = plain.status == Status.CONVERGED
        assert np.abs(fast.t[conv] - plain.t[conv]).max() < 1e-9
        return
    # the hybrid: each run's CONVERGED rays at the exact first hit, no silent miss, no false hit;
    # the runs differ only in which rays near a surface end UNCERTIFIED
    exact = _exact_or_inf(scene, o, d)
    for run in (plain, fast):
        conv = run.status == Status.CONVERGED
        assert np.all(np.isfinite(exact[conv])) and np.abs(run.t[conv] - exact[conv]).max() < 1e-9
        assert not np.any((run.status == Status.MISS) & np.isfinite(exact))
        assert np.all(np.isin(run.status, (Status.CONVERGED, Status.MISS, Status.UNCERTIFIED)))
    # (with neither, at the default knobs, all but the grazing rays' hits are CONVERGED: every hit
    # whose depth float64 resolves to xtol, depth_resolved, and all but 2 of the others)
    default = _run(method, scene, o, d, backend, xtol=1e-12)
    sure = depth_resolved(method, scene, o, d, exact, {"xtol": 1e-12})
    assert np.all(default.status[sure] == Status.CONVERGED)
    assert (default.status == Status.CONVERGED).sum() >= sure.sum() - 2


def test_ladder_steps_take_grazing_misses_to_the_same_verdicts():
    """A ray passing a sphere at distance δ needs about π/√(2δ) certified steps (each at most
    twice |φ|, φ ≈ δ + s²/2 along the ray); ladder steps take 16 samples per loop step, each pair
    a step against ``max_steps`` (every sample counted in evals).  Without the ray bounds: the padded ball would cut these rays short.
    At δ = 3e-5 the spheres near the closest approach (radius ≈ δ) no longer cover a forced step
    of ``min_step`` = 1e-4, which stands uncertified: that MISS is not certified (UNCERTIFIED), and
    only from there does the hybrid go on in ladder steps (before, its ladder's forced spacing would
    stand uncertified near a surface the ray is about to cross)."""
    scene = Sphere()
    o, d = _grazing_sphere_rays([1e-3, 1e-4, 3e-5])
    plain = _run("hybrid_secant", scene, o, d, ladder=0, bounds=0)
    fast = _run("hybrid_secant", scene, o, d, bounds=0)
    expected = [Status.MISS, Status.MISS, Status.UNCERTIFIED]
    np.testing.assert_array_equal(plain.status, expected)
    np.testing.assert_array_equal(fast.status, expected)
    assert np.all(np.isinf(plain.t)) and np.all(np.isinf(fast.t))
    assert plain.iterations[1] > 200  # certification's cost at δ = 1e-4: about π/√(2δ) = 222 steps
    np.testing.assert_array_equal(fast.iterations[:2], plain.iterations[:2])
    # the third went on in ladder steps (spaced by the forced step, which doubles after each ladder
    # that stands), with samples evaluated past the bound it ended at
    assert fast.evals[2] > fast.iterations[2] + 1 and plain.evals[2] == plain.iterations[2] + 1
    assert np.all(fast.evals >= fast.iterations)


def test_extrapolation_crosses_a_shallow_approach_in_few_steps():
    """A ray closing in on a box face at 1°–5° (slope σ = sin θ): the over-relaxed march leaves
    (1 − σ)/(1 + σ) of the distance D to the face per step, so certifying the approach to within
    ``min_step`` takes about ln(D/min_step)/ln((1 + σ)/(1 − σ)) steps (the floor of any certified
    method, bench/studies/cost_floor.py), then its crossing step brackets the face.  The plain IDR
    march (``extrapolate`` 0) shortens its steps by 1 − σ each, down to forced steps of min_step
    that no sphere covers on the face: its crossing is UNCERTIFIED.  ``reach`` does not matter:
    the crossing step is taken only once its uncertified stretch is under min_step."""
    scene = Box((0.5, 0.5, 0.5))
    theta = np.radians([1.0, 2.0, 5.0])
    exact = 0.04 / np.sin(theta)  # from 0.04 above the top face to its centre
    o = np.column_stack([-exact * np.cos(theta), np.zeros(3), np.full(3, 0.54)])
    d = np.column_stack([np.cos(theta), np.zeros(3), -np.sin(theta)])
    # (xtol 1e-10: at 1° φ's sign is rounding over about 1e-12 of the ray, wider than the default
    # 1e-12 closes on: MarchRefine.closing_width)
    slow = _run("hybrid_secant", scene, o, d, extrapolate=0.0, ladder=0, bounds=0, xtol=1e-10)  # (the slab test
    fast = _run("hybrid_secant", scene, o, d, ladder=0, bounds=0, xtol=1e-10)  # would start these rays on the face)
    assert np.all(fast.status == Status.CONVERGED) and np.all(slow.status == Status.UNCERTIFIED)
    np.testing.assert_allclose(fast.t, exact, rtol=0, atol=1e-10)
    np.testing.assert_allclose(slow.t, exact, rtol=0, atol=1e-10)
    sigma = np.sin(theta)
    floor = np.log(exact / 1e-4) / np.log((1 + sigma) / (1 - sigma))
    assert np.all(fast.iterations <= 1.1 * floor + 10), (fast.iterations, floor)
    assert np.all(fast.iterations < slow.iterations)
    far = _run("hybrid_secant", scene, o, d, ladder=0, bounds=0, reach=1e9, xtol=1e-10)
    np.testing.assert_array_equal(far.iterations, fast.iterations)


@pytest.mark.parametrize("backend", ["numpy", pytest.param("jax:cpu", marks=pytest.mark.slow)])
def test_reach_changes_the_steps_not_the_hits(backend):
    """``reach`` bounds the extrapolated step; a step is accepted only if it crosses or is
    certified, so every reach finds the same crossings (torus ∪ box camera and grazing rays)."""
    pytest.importorskip(backend.split(":")[0])
    scene, o, d = _torus_box_camera_and_grazing_rays()
    exact = _exact_or_inf(scene, o, d)
    hit = np.isfinite(exact)
    runs = {reach: _run("hybrid_secant", scene, o, d, backend, reach=reach) for reach in (0.0, 0.01, 0.1, 1e9)}
    # the rays 3e-7 outside and 1e-5 inside the equator pass within min_step of the surface: forced
    # steps no sphere covers stand there, so neither the MISS nor the crossing after them is
    # certified; so do two camera rays at the torus's silhouette
    first = runs[0.0].status
    assert first[len(o) - 4] == first[len(o) - 2] == Status.UNCERTIFIED
    assert np.sum(first == Status.UNCERTIFIED) <= 0.01 * len(o)
    for r in runs.values():
        np.testing.assert_array_equal(r.status, first)
        conv = r.status == Status.CONVERGED
        assert np.all(hit[conv]) and np.abs(r.t[conv] - exact[conv]).max() < 1e-9
        assert np.all(hit[r.status == Status.CONVERGED]) and not np.any(hit & (r.status == Status.MISS))
    # a crossing step at all saves steps (reach 0 leaves the approach to the over-relaxed steps,
    # which close in on the surface only geometrically); how far it may reach does not matter
    assert runs[0.1].evals.sum() == runs[1e9].evals.sum() < runs[0.0].evals.sum()


@pytest.mark.parametrize("knob,value", [("ladder", -2), ("ladder", 1.5), ("ladder_after", -2), ("extrapolate", -0.5),
                                        ("reach", -1.0)])
def test_bad_ladder_knobs_name_the_knob(knob, value):
    case = get_case("csg.union.camera.32x32")
    with pytest.raises(ValueError, match=knob):
        registry.resolve("numpy").prepare("hybrid_secant", case.scene, case.origins, case.directions, **{knob: value})


@pytest.mark.parametrize("backend,ladder", [("numpy", 16), ("torch", 16), ("jax:cpu", 0)])
@pytest.mark.parametrize("method", ["march_secant", "hybrid_secant"])
def test_the_default_ladder_is_the_drivers_choice(backend, ladder, method):
    """``ladder`` = -1 (the default) leaves it to the loop driver for the constant-step marchers: 16
    samples on the compacting drivers, none on jax's masked levels (impls.jax.driver.LADDER); the
    hybrids take ladder steps only once past the frontier by ``min_step`` (the ray 1e-5 from the
    sphere), where no answer can be certified any more (the next test)."""
    pytest.importorskip(backend.split(":")[0])
    scene = Sphere()
    o, d = _grazing_sphere_rays([1e-3, 1e-5, -1e-4])
    default = _run(method, scene, o, d, backend, bounds=0)
    explicit = _run(method, scene, o, d, backend, bounds=0, ladder=ladder)
    np.testing.assert_array_equal(default.iterations, explicit.iterations)
    np.testing.assert_array_equal(default.evals, explicit.evals)
    assert (default.evals > default.iterations + 1).any() == (ladder > 1)


@pytest.mark.parametrize("backend", ["numpy", "torch:cpu", "numba", "warp",
                                     pytest.param("jax:cpu", marks=pytest.mark.slow)])
@pytest.mark.parametrize("method", ["march_secant", "march_bisect", "march_newton"])
def test_a_march_that_starts_on_the_surface_exactly_is_uncertified(backend, method):
    """φ = 0 exactly at the start shows no side of the surface, and the first crossing lies
    strictly after the start (reference.scene.first_hit_from_intervals): a ray leaving a sphere
    from a point of it has no crossing, one entering it crosses at the far side.  The marches
    reported CONVERGED at t_min for both (found with rays from a sphere's centre and t_min its
    radius); now UNCERTIFIED, as the certified methods have been; other rays are unchanged."""
    from tests.conftest import require_method, resolve_or_skip

    b = resolve_or_skip(backend)
    require_method(b, method)
    ball = Sphere(center=(0.0, 0.0, 0.0), radius=1.0)
    # starts on the sphere at t_min: out of it along +z, into it along −z (φ(o) = 0 exactly: |o| = 1)
    o = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 3.0]])
    d = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [0.0, 0.0, -1.0]])
    assert np.all(ball.value(o[:2], np) == 0.0)
    p = b.prepare(method, ball, o, d, dtype="float64", t_min=0.0, t_max=10.0, step=0.01)
    res = p.result(p.run())
    assert list(res.status[:2]) == [Status.UNCERTIFIED] * 2, res.status
    assert res.status[2] == Status.CONVERGED and abs(res.t[2] - 2.0) < 1e-9


@pytest.mark.parametrize("backend", ["numpy", "torch:cpu", "numba", "warp",
                                     pytest.param("jax:cpu", marks=pytest.mark.slow)])
@pytest.mark.parametrize("method", ["march_secant", "march_bisect", "march_newton"])
def test_a_march_certifies_a_miss_only_where_its_samples_spheres_cover_the_ray(backend, method):
    """A spherical shell 1e-4 thick, radius 0.5, seen from z = 3 at step 0.02: every ray through
    it crosses it twice within one step or two, which a constant-step march does not see.  Such a
    ray was a MISS (64² rays: all 1,280 that cross the shell, on numpy); a MISS is now
    certified only where each step's end spheres overlap (rc₀ + rc₁ ≥ step), so these rays are
    UNCERTIFIED (depth inf), and rays that pass the shell by more than half a step stay MISS."""
    from reference import Difference, rays
    from tests.conftest import require_method, resolve_or_skip

    b = resolve_or_skip(backend)
    require_method(b, method)
    shell = Difference(Sphere(center=(0.0, 0.0, 0.0), radius=0.5 + 1e-4), Sphere(center=(0.0, 0.0, 0.0), radius=0.5))
    o, d = rays.pinhole(eye=(0.05, 0.02, 3.0), look_at=(0.0, 0.0, 0.0), fov_deg=30.0, width=64, height=64)
    p = b.prepare(method, shell, o, d, dtype="float64", t_min=0.0, t_max=10.0, step=0.02, ladder=0)
    res = p.result(p.run())
    hit = np.isfinite(shell.first_hit(o, d, 0.0))
    # the ray's closest approach to the centre: farther than 0.5 + 1e-4 + step/2 clears every step
    far = np.linalg.norm(np.cross(o, d), axis=1) > 0.5 + 1e-4 + 0.01 * (1 + 1e-6)
    assert hit.sum() > 1000 and far.sum() > 1000
    assert not np.any(res.status[hit] == Status.MISS), int(np.sum(res.status[hit] == Status.MISS))
    assert np.all(np.isin(res.status[hit], (Status.CONVERGED, Status.UNCERTIFIED)))
    assert np.all(res.status[far] == Status.MISS)
    assert np.all(np.isinf(res.t[~hit]))


@pytest.mark.parametrize(("backend", "method"), _march_cases())
@pytest.mark.parametrize("ladder", [0, 16])
def test_a_march_certifies_a_crossing_as_the_first_only_where_its_samples_spheres_reach_it(backend, method, ladder):
    """The 1e-4 shell of the test above in front of a wall (the plane z = −1), step 0.02: a ray
    through the shell crosses it twice within a step or two, and the march, not seeing it,
    brackets the wall behind.  That was CONVERGED, about 3 past the first crossing (64² rays:
    all 1,280 through the shell).  A crossing is now CONVERGED only where the covered stretch
    from the start (the frontier g) reaches within a step of its bracket, so the depth is within
    step + xtol of the first crossing (ConstantStep); these rays are UNCERTIFIED, with the
    wall's depth, and the rays passing the shell by more than half a step still converge on it."""
    from reference import Difference, Plane, Union, rays
    from tests.conftest import require_method, resolve_or_skip

    b = resolve_or_skip(backend)
    require_method(b, method)
    shell = Difference(Sphere(center=(0.0, 0.0, 0.0), radius=0.5 + 1e-4), Sphere(center=(0.0, 0.0, 0.0), radius=0.5))
    scene = Union(shell, Plane(normal=(0.0, 0.0, 1.0), offset=-1.0))  # φ = z + 1
    o, d = rays.pinhole(eye=(0.05, 0.02, 3.0), look_at=(0.0, 0.0, 0.0), fov_deg=30.0, width=64, height=64)
    step, xtol = 0.02, 1e-10
    p = b.prepare(method, scene, o, d, dtype="float64", t_min=0.0, t_max=10.0, step=step, xtol=xtol, ladder=ladder)
    res = p.result(p.run())
    exact = scene.first_hit(o, d, 0.0)
    wall = -(1.0 + o[:, 2]) / d[:, 2]
    assert np.all(np.isfinite(exact))
    shell_first = exact < wall - 1.0
    far = np.linalg.norm(np.cross(o, d), axis=1) > 0.5 + 1e-4 + step / 2 * (1 + 1e-6)
    assert shell_first.sum() > 1000 and far.sum() > 1000
    conv = res.status == Status.CONVERGED
    err = np.abs(res.t - exact)
    assert np.all(err[conv] <= step + xtol), float(err[conv].max())
    assert not np.any(conv[shell_first]), int(conv[shell_first].sum())
    assert np.all(res.status[shell_first] == Status.UNCERTIFIED)
    assert np.all(conv[far]) and np.all(err[far] <= 1e-9)


@pytest.mark.parametrize(("backend", "method"), _march_cases())
def test_a_march_takes_no_crossing_from_a_sample_that_shows_no_side(backend, method):
    """Rays lying in a face plane of the box [−1, 1]³ (|z| = 1 exactly) have φ = 0 exactly
    wherever they run along the face: they touch the surface, they do not cross it.  The
    marches took the first φ = 0 sample as a crossing and reported it CONVERGED (as float32 did
    on the stability suite's ``box.parallel`` rays 1e-9 outside a face, rounded onto it).  A sign
    change to or from an unresolved sample (certified radius 0) is now UNCERTIFIED at that
    sample; rays 1e-3 inside the face plane still converge on the box's side wall."""
    from reference import Box
    from tests.conftest import require_method, resolve_or_skip

    b = resolve_or_skip(backend)
    require_method(b, method)
    box = Box((1.0, 1.0, 1.0))
    rng = np.random.default_rng(3)
    n = 64
    o = np.stack([np.full(n, -3.0), rng.uniform(-0.9, 0.9, n), np.where(np.arange(n) % 2 == 0, 1.0, 1.0 - 1e-3)], axis=1)
    o[1::4, 2] *= -1.0  # (both faces, z = 1 and z = −1)
    o[::4, 2] *= -1.0
    d = np.tile([1.0, 0.0, 0.0], (n, 1))
    touch = np.abs(o[:, 2]) == 1.0
    assert np.all(box.value(o[touch] + 2.5 * d[touch]) == 0.0)
    p = b.prepare(method, box, o, d, dtype="float64", t_min=0.0, t_max=10.0, step=0.01)
    res = p.result(p.run())
    assert np.all(res.status[touch] == Status.UNCERTIFIED), res.status[touch]
    assert np.all(res.status[~touch] == Status.CONVERGED), res.status[~touch]
    np.testing.assert_allclose(res.t[~touch], 2.0, rtol=0, atol=1e-9)


@pytest.mark.parametrize("method", ["march_secant", "hybrid_secant"])
@pytest.mark.parametrize("max_steps", [300, 4096])
def test_a_budget_ends_a_ray_at_the_same_step_with_or_without_ladder_steps(method, max_steps):
    """``max_steps`` counts steps, a ladder's pairs one by one.  Before, a ladder step counted once:
    on the plane camera (t_max 50: 5,000 constant steps of 0.01 to the far end) numpy's and torch's
    marches, which take ladder steps by default, certified 224 rays MISS within 373 loop steps where
    jax and numba, which take none, spent the 4,096-step budget (MAX_ITER): the same knobs, other
    statuses.  Now a ray whose budget runs out mid-ladder ends on the last pair it may take."""
    case = get_case("plane.camera.32x32")
    o, d = case.origins, case.directions

    def run(**kw):
        b = registry.resolve("numpy")
        p = b.prepare(method, case.scene, o.copy(), d.copy(), dtype="float64", t_min=case.t_min, t_max=case.t_max,
                      max_steps=max_steps, **kw)
        return p.result(p.run())

    plain, fast = run(ladder=0), run(ladder=16, ladder_after=4)
    np.testing.assert_array_equal(fast.status, plain.status)
    assert fast.iterations.max() <= max_steps and plain.iterations.max() <= max_steps
    if method == "march_secant":  # the same samples: the same steps and (to rounding) depths
        assert np.abs(fast.iterations - plain.iterations).max() <= 1
        maxed = plain.status == Status.MAX_ITER
        assert maxed.sum() >= 200 and np.all(fast.iterations[maxed] == max_steps)
        np.testing.assert_allclose(fast.t[np.isfinite(plain.t)], plain.t[np.isfinite(plain.t)], rtol=1e-12)


@pytest.mark.parametrize("backend", ["torch:cpu", "numba", "warp", pytest.param("jax:cpu", marks=pytest.mark.slow)])
def test_every_backend_spends_a_march_budget_as_numpy_does(backend):
    """The plane camera's march at its default knobs (each backend's own ladder choice): the same
    status on every ray as numpy's, MAX_ITER where the budget ends before t_max."""
    status = _statuses_beside_numpy(backend, "plane.camera.32x32", "march_secant")
    assert (status == Status.MAX_ITER).sum() == 256


def _statuses_beside_numpy(backend: str, case_id: str, method: str, **knobs) -> np.ndarray:
    """``method`` at its default knobs (but ``knobs``) on the catalog case on numpy and ``backend``:
    the statuses, after checking that they are the same on every ray."""
    from tests.conftest import resolve_or_skip

    case = get_case(case_id)
    got = {}
    for bid in ("numpy", backend):
        b = resolve_or_skip(bid)
        p = b.prepare(method, case.scene, case.origins.copy(), case.directions.copy(), dtype="float64",
                      t_min=case.t_min, t_max=case.t_max, **knobs)
        got[bid] = p.result(p.run()).status
    np.testing.assert_array_equal(got[backend], got["numpy"])
    return got["numpy"]


#: the mesh blob's grazing hits are crossed at slopes ~1e-4, where φ's sign is rounding over more of the
#: ray than the default xtol (1e-12): at that xtol they are all UNCERTIFIED (MarchRefine.closing_width),
#: at 1e-10 the 87 that the march certifies the first are CONVERGED (depth error ≤ 2.6e-14)
GRAZING_XTOL = {"xtol": 1e-10}


def test_a_hybrids_ladder_steps_leave_every_certified_answer_as_single_steps_give_it():
    """A hybrid's ladder steps are spaced by the forced step and take no crossing step, so near a
    surface they passed thin crossings that single steps find: on the mesh blob's grazing rays
    numpy's ``hybrid_secant`` at its driver's ladder (16) certified 19 of 256 hits where jax and
    numba (no ladder) certified 87.  A ray now goes on in ladder steps only once it is past the
    frontier of its certified stretch by ``min_step``, where no crossing can be certified any more
    (a CONVERGED depth is within min_step of the frontier, a MISS needs none): the ladder changes
    no certified answer, and here no status."""
    for cid in ("mesh.blob.grazing.1e-9", "neural.blob.camera.16x16"):
        case = get_case(cid)
        o, d = case.origins, case.directions

        def run(**kw):
            b = registry.resolve("numpy")
            p = b.prepare("hybrid_secant", case.scene, o.copy(), d.copy(), dtype="float64", t_min=case.t_min,
                          t_max=case.t_max, **GRAZING_XTOL, **kw)
            return p.result(p.run())

        plain, ladder = run(ladder=0), run(ladder=16)
        assert (ladder.evals > ladder.iterations + 1).any()  # ladder steps were taken
        np.testing.assert_array_equal(ladder.status, plain.status)
        conv = plain.status == Status.CONVERGED
        assert conv.sum() >= (87 if cid.startswith("mesh") else 100)
        np.testing.assert_allclose(ladder.t[conv], plain.t[conv], rtol=0, atol=1e-12)


@pytest.mark.parametrize("backend", ["torch:cpu", "warp", pytest.param("jax:cpu", marks=pytest.mark.slow)])
def test_every_backend_certifies_the_grazing_mesh_hits_numpy_does(backend):
    """``hybrid_secant`` at its defaults (each driver's own ladder) on the mesh blob's grazing rays:
    the same status on every ray as numpy's (they were 19 CONVERGED on the laddered drivers, 87
    on jax's)."""
    status = _statuses_beside_numpy(backend, "mesh.blob.grazing.1e-9", "hybrid_secant", **GRAZING_XTOL)
    assert (status == Status.CONVERGED).sum() >= 87
