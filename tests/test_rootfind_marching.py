"""The marching stage's two accelerations (impls.core.rootfind.MarchRefine): ladder steps for rays
still marching after ``ladder_after`` steps, and the extrapolated forced step of the hybrid.  They
change how many loop iterations a ray takes, not which crossing it finds."""

from __future__ import annotations

import numpy as np
import pytest

from impls import Status, registry
from reference import Box, Sphere
from reference.cases import get_case


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


def _exact_or_inf(scene, o, d):
    t = scene.first_hit(o, d, 0.0)
    return np.where(t <= 10.0, t, np.inf)


@pytest.mark.parametrize("backend", ["numpy", "torch"])
@pytest.mark.parametrize("method", ["hybrid_secant", "march_secant", "march_bisect"])
def test_ladder_and_extrapolation_find_the_same_hits(backend, method):
    if backend == "torch":
        pytest.importorskip("torch")
    scene, o, d = _torus_box_camera_and_grazing_rays()
    extra = {"extrapolate": 0.0} if method == "hybrid_secant" else {}
    plain = _run(method, scene, o, d, backend, xtol=1e-12, ladder=0, **extra)
    fast = _run(method, scene, o, d, backend, xtol=1e-12, ladder_after=4)
    assert (fast.evals > fast.iterations + 1).any()  # ladder steps were taken
    assert fast.iterations.max() < plain.iterations.max()
    np.testing.assert_array_equal(fast.status, plain.status)
    conv = plain.status == Status.CONVERGED
    assert np.abs(fast.t[conv] - plain.t[conv]).max() < 1e-9
    if method == "hybrid_secant":  # (constant-step marching misses crossings with chords under its step)
        exact = _exact_or_inf(scene, o, d)
        assert np.array_equal(np.isfinite(exact), conv)
        assert np.abs(fast.t[conv] - exact[conv]).max() < 1e-9


def test_ladder_cuts_the_iterations_of_grazing_misses():
    """A ray passing a sphere at distance δ needs about π/√(2δ) certified steps (each at most
    twice |φ|, φ ≈ δ + s²/2 along the ray); ladder steps take 16 samples per iteration (every
    sample counted in evals).  Without the ray bounds: the padded ball would cut these rays short.
    At δ = 3e-6 the spheres near the closest approach (radius ≈ δ) no longer cover a forced step
    of ``min_step`` = 1e-5, which stands uncertified: that MISS is not certified (UNCERTIFIED)."""
    scene = Sphere()
    o, d = _grazing_sphere_rays([1e-3, 1e-5, 3e-6])
    plain = _run("hybrid_secant", scene, o, d, ladder=0, bounds=0)
    fast = _run("hybrid_secant", scene, o, d, bounds=0)
    expected = [Status.MISS, Status.MISS, Status.UNCERTIFIED]
    np.testing.assert_array_equal(plain.status, expected)
    np.testing.assert_array_equal(fast.status, expected)
    assert np.all(np.isinf(plain.t)) and np.all(np.isinf(fast.t))
    assert plain.iterations[-1] > 1000  # certification's cost at δ = 3e-6
    assert np.all(fast.iterations[1:] * 5 < plain.iterations[1:])
    assert np.all(fast.evals >= fast.iterations)


def test_extrapolation_crosses_a_shallow_approach_in_few_steps():
    """A ray closing in on a box face at 1°–5°: sphere tracing shortens its steps geometrically
    (ratio about 1 − sin θ); the secant through the last two points aims past the crossing as
    soon as it lies within ``reach`` (0.1) of the ray: measured 661 → 157 iterations at 1°, and
    4 with no limit on the reach (a plane's secant is exact)."""
    scene = Box((0.5, 0.5, 0.5))
    theta = np.radians([1.0, 2.0, 5.0])
    exact = 0.04 / np.sin(theta)  # from 0.04 above the top face to its centre
    o = np.column_stack([-exact * np.cos(theta), np.zeros(3), np.full(3, 0.54)])
    d = np.column_stack([np.cos(theta), np.zeros(3), -np.sin(theta)])
    slow = _run("hybrid_secant", scene, o, d, extrapolate=0.0, ladder=0, bounds=0)  # (the slab test would start
    fast = _run("hybrid_secant", scene, o, d, ladder=0, bounds=0)  # these rays on the face)
    assert np.all(fast.status == Status.CONVERGED) and np.all(slow.status == Status.CONVERGED)
    np.testing.assert_allclose(fast.t, exact, rtol=0, atol=1e-10)
    np.testing.assert_allclose(slow.t, exact, rtol=0, atol=1e-10)
    assert np.all(fast.iterations < 0.6 * slow.iterations)
    far = _run("hybrid_secant", scene, o, d, ladder=0, bounds=0, reach=1e9)
    np.testing.assert_allclose(far.t, exact, rtol=0, atol=1e-10)
    assert np.all(far.iterations <= 10)


@pytest.mark.parametrize("backend", ["numpy", pytest.param("jax:cpu", marks=pytest.mark.slow)])
def test_reach_changes_the_steps_not_the_hits(backend):
    """``reach`` bounds the extrapolated step; a step is accepted only if it crosses or is
    certified, so every reach finds the same crossings (torus ∪ box camera and grazing rays)."""
    pytest.importorskip(backend.split(":")[0])
    scene, o, d = _torus_box_camera_and_grazing_rays()
    exact = _exact_or_inf(scene, o, d)
    hit = np.isfinite(exact)
    runs = {reach: _run("hybrid_secant", scene, o, d, backend, reach=reach) for reach in (0.0, 0.01, 0.1, 1e9)}
    expected = np.where(hit, Status.CONVERGED, Status.MISS)
    # the ray 3e-7 outside the equator passes within min_step of the surface: forced steps no
    # sphere covers stand there, so its MISS is not certified
    expected[len(o) - 4] = Status.UNCERTIFIED
    for r in runs.values():
        np.testing.assert_array_equal(r.status, expected)
        assert np.abs(r.t[hit] - exact[hit]).max() < 1e-9
    # extrapolating at all saves steps; how far (0.01 or 0.1) is nearly a wash once the jump's
    # stretch must be certified (a longer jump leaves more of it to cover)
    assert max(runs[0.1].evals.sum(), runs[0.01].evals.sum()) < runs[0.0].evals.sum()


@pytest.mark.parametrize("knob,value", [("ladder", -2), ("ladder", 1.5), ("ladder_after", -2), ("extrapolate", -0.5),
                                        ("reach", -1.0)])
def test_bad_ladder_knobs_name_the_knob(knob, value):
    case = get_case("csg.union.camera.32x32")
    with pytest.raises(ValueError, match=knob):
        registry.resolve("numpy").prepare("hybrid_secant", case.scene, case.origins, case.directions, **{knob: value})


@pytest.mark.parametrize("backend,ladder", [("numpy", 16), ("torch", 16), ("jax:cpu", 0)])
def test_the_default_ladder_is_the_drivers_choice(backend, ladder):
    """``ladder`` = -1 (the default) leaves it to the loop driver: 16 samples on the compacting
    drivers, none on jax's masked levels (impls.jax.driver.LADDER)."""
    pytest.importorskip(backend.split(":")[0])
    scene = Sphere()
    o, d = _grazing_sphere_rays([1e-3, 1e-5, -1e-4])
    default = _run("hybrid_secant", scene, o, d, backend, bounds=0)
    explicit = _run("hybrid_secant", scene, o, d, backend, bounds=0, ladder=ladder)
    np.testing.assert_array_equal(default.iterations, explicit.iterations)
    np.testing.assert_array_equal(default.evals, explicit.evals)
    assert (default.evals > default.iterations + 1).any() == (ladder > 1)
