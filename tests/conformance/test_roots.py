"""Root finders against exact first hits: depths, statuses, evaluation counts, batching,
over-relaxation, knob errors."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from impls import METHODS, Status, registry
from impls.core.methods_root import checks_inside
from reference import Sphere
from reference.rays import normalize
from reference.scene import Field, norm
from tests.conformance.common import (ROOT_METHODS, SCENES, SPHERE, TIGHT, LambdaField, applicable, camera,
                                      depth_resolved, run,
                                      skip_unless_offered, xfail_if_expected)


@functools.lru_cache(maxsize=None)
def _clear_by_half_a_step(scene_name: str, step: float) -> np.ndarray:
    """The :func:`camera` rays along which φ/L stays above half a ``step`` over [0, 10]: there a
    constant-step march's samples' spheres cover every step (rc₀ + rc₁ ≥ step), so it certifies
    their MISS.  Found by dense sampling at spacing s, less what it can miss below its smallest
    sample (L·s/2); computed once per scene and step, shared by every backend (read only)."""
    scene = SCENES[scene_name]
    o, d = camera()
    lip, s = scene.info.lipschitz, 1e-4
    ts = np.arange(0.0, 10.0 + s, s)
    low = np.array([np.min(scene.value(o[i] + ts[:, None] * d[i])) for i in range(len(o))])
    clear = low / lip - s / 2 > step / 2 * (1 + 1e-9)
    clear.flags.writeable = False
    return clear


@pytest.mark.parametrize("scene_name", sorted(SCENES))
@pytest.mark.parametrize("method", ROOT_METHODS)
def test_root_depth_against_exact(any_backend, method, scene_name):
    scene = SCENES[scene_name]
    if not applicable(method, scene):
        pytest.skip(METHODS[method].skip_reason(scene))
    o, d = camera()
    exact = scene.first_hit(o, d, 0.0)
    hit = np.isfinite(exact)
    assert hit.any() and (~hit).any()
    r = run(any_backend, method, scene, o, d, **TIGHT[method])
    # (sphere tracing's tight tol is below what float64 resolves on the most oblique hits: those
    # may be UNCERTIFIED, with their depths; depth_resolved says which)
    must = depth_resolved(method, scene, o, d, exact, TIGHT[method])
    if method.startswith("march_") and checks_inside(scene):
        # a bound taken on trust covers no march step: the frontier stays at the ray's start, and a
        # crossing further than a step from it is not certified the first (ConstantStep), so the
        # march's hits here are UNCERTIFIED (with their depths, checked below)
        assert np.all(exact[hit] > TIGHT[method]["step"])
        must = np.zeros_like(hit)
    else:
        assert must.sum() >= 0.8 * hit.sum()
    assert np.all(r.status[must] == Status.CONVERGED), r.status_counts()
    assert np.all(np.isin(r.status[hit], (Status.CONVERGED, Status.UNCERTIFIED))), r.status_counts()
    if method.startswith("march_") and checks_inside(scene):
        # (a bound taken on trust — this module's own Field subclasses — covers no step: the march's
        # MISS is certified only by the ray bounds, before any step)
        assert np.all(np.isin(r.status[~hit], (Status.MISS, Status.UNCERTIFIED))), r.status_counts()
    elif method.startswith("march_"):
        clear = _clear_by_half_a_step(scene_name, TIGHT[method]["step"])
        assert np.all(~hit[clear]) and clear.sum() >= 0.5 * (~hit).sum()
        assert np.all(r.status[clear] == Status.MISS), r.status_counts()
        assert np.all(np.isin(r.status[~hit], (Status.MISS, Status.UNCERTIFIED))), r.status_counts()
    else:
        assert np.all(r.status[~hit] == Status.MISS), r.status_counts()
    assert np.all(np.isinf(r.t[~hit]))
    err = np.abs(r.t[hit] - exact[hit])
    assert err.max() <= 1e-9, f"max depth error {err.max():.3g}"
    assert np.all(r.evals[hit] >= 1) and np.all(r.evals >= 0) and np.all(r.iterations >= 0)


@pytest.mark.parametrize("method", ROOT_METHODS)
def test_root_batched_equals_per_ray_loop(any_backend, method):
    o, d = camera(5)
    r = run(any_backend, method, SPHERE, o, d, **TIGHT[method])
    for i in range(0, len(o), 3):
        ri = run(any_backend, method, SPHERE, o[i:i + 1], d[i:i + 1], **TIGHT[method])
        assert ri.status[0] == r.status[i] and ri.iterations[0] == r.iterations[i] and ri.evals[0] == r.evals[i]
        np.testing.assert_allclose(ri.t[0], r.t[i], rtol=1e-14, atol=0)


class CountingField(Field):
    """Wraps a scene and counts the points φ is evaluated at (the ground truth for ``evals``)."""

    kind = "counting"

    def __init__(self, inner):
        self.inner = inner
        self.points = 0

    @property
    def info(self):
        return self.inner.info

    def value(self, x, xp=np, theta=None):
        self.points += int(np.prod(tuple(x.shape[:-1])))
        return self.inner.value(x, xp, theta)


@pytest.mark.parametrize("method", ROOT_METHODS)
def test_reported_evals_equal_counted_calls(request, any_backend, method):
    xfail_if_expected(request, any_backend, "eval_count")
    scene = CountingField(SPHERE)
    o, d = camera(6)
    r = run(any_backend, method, scene, o, d, **TIGHT[method])
    assert int(r.evals.sum()) == scene.points


@pytest.mark.parametrize("method", ["hybrid_secant", "march_secant"])
def test_reported_evals_equal_counted_calls_in_ladder_steps(request, any_backend, method):
    """Ladder steps evaluate ``ladder`` samples per ray per loop step, every one counted."""
    xfail_if_expected(request, any_backend, "eval_count")
    scene = CountingField(SPHERE)
    o, d = camera(6)
    if METHODS[method].family == "root" and "min_step" in {k.name for k in METHODS[method].knobs}:
        # the hybrids go on in ladder steps only once a step stood uncertified: rays passing the
        # sphere 1e-5 away (nearer than min_step) do, searched without the ray bounds (which they miss)
        c, rad = np.array(SPHERE.center), SPHERE.radius
        o = np.concatenate([o, c + [[-3.0, rad + 1e-5, 0.0], [-3.0, 0.0, rad + 2e-5]]])
        d = np.concatenate([d, [[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]])
        extra = {"bounds": 0}
    else:
        extra = {}
    r = run(any_backend, method, scene, o, d, **TIGHT[method], ladder_after=1, ladder=5, **extra)
    assert (r.evals > r.iterations + 1).any()  # ladder steps were taken
    assert int(r.evals.sum()) == scene.points


def grazing_rays():
    """Rays tangent-ish to the sphere (impact parameter 1 ± 1e-3), plus one NaN ray."""
    o = np.tile([[-3.0, 0.0, 0.0]], (3, 1))
    b = np.array([0.8 * (1 - 1e-3), 0.8 * (1 + 1e-3), 0.0])
    o[:, 1] = b - 0.2
    o[:, 2] = 0.05
    o[:, 0] += 0.1
    d = np.tile([[1.0, 0.0, 0.0]], (3, 1))
    o[2] = np.nan
    return o, d


@pytest.mark.filterwarnings("ignore:invalid value:RuntimeWarning")  # the NaN field below, on purpose
def test_every_root_status_is_produced_on_purpose(any_backend):
    o, d = grazing_rays()
    seen = set()
    r = run(any_backend, "sphere_trace", SPHERE, o, d, tol=1e-12, max_steps=5)  # budget too small
    assert r.status[0] == Status.MAX_ITER and r.status[2] == Status.BAD_INPUT
    seen |= set(r.status.tolist())
    r = run(any_backend, "hybrid_secant", SPHERE, o, d, xtol=1e-12)
    assert r.status[0] == Status.CONVERGED and r.status[1] == Status.MISS
    seen |= set(r.status.tolist())

    nan_field = LambdaField(lambda x, xp: xp.log(x[..., 0] - 100.0))  # NaN everywhere here
    r = run(any_backend, "sphere_trace", nan_field, o[:2], d[:2], tol=1e-9, max_steps=10)
    assert np.all(r.status == Status.NON_FINITE) and np.all(np.isnan(r.t))
    seen |= set(r.status.tolist())
    assert {Status.CONVERGED, Status.MISS, Status.MAX_ITER, Status.NON_FINITE, Status.BAD_INPUT} <= seen



def test_over_relaxation_is_safe(any_backend):
    o, d = camera(10)
    exact = SPHERE.first_hit(o, d, 0.0)
    hit = np.isfinite(exact)
    plain = run(any_backend, "sphere_trace", SPHERE, o, d, tol=1e-12, max_steps=5000, omega=1.0)
    relaxed = run(any_backend, "sphere_trace", SPHERE, o, d, tol=1e-12, max_steps=5000, omega=1.6)
    assert np.all(relaxed.status[hit] == Status.CONVERGED) and np.all(relaxed.status[~hit] == Status.MISS)
    assert np.abs(relaxed.t[hit] - exact[hit]).max() <= 1e-9
    # (not asserted: fewer evaluations; on this convex scene ω = 1.6 costs ~3% more than ω = 1)
    assert plain.evals.sum() > 0


def test_over_relaxation_does_not_tunnel_through_a_thin_shell(any_backend):
    """A shell of thickness 0.02 (|φ_sphere| − 0.01): ω close to 2 would jump across it."""

    shell = LambdaField(lambda x, xp: xp.abs(norm(xp, x) - 1.0) - 0.01)
    o = np.array([[0.0, 0.0, 3.0]])
    d = normalize(np.array([[0.0, 0.3, -1.0]]))
    r = run(any_backend, "sphere_trace", shell, o, d, tol=1e-12, max_steps=5000, omega=1.95)
    # exact first hit of |x| = 1.01 along the ray
    exact = Sphere(radius=1.01).first_hit(o, d)[0]
    assert r.status[0] == Status.CONVERGED and abs(r.t[0] - exact) <= 1e-9


def test_jax_jitted_equals_eager():
    b = registry.resolve("jax:cpu")
    if isinstance(b, registry.Unavailable):
        pytest.skip(b.reason)
    import jax.numpy as jnp

    o, d = camera(6)
    jitted = run(b, "march_newton", SPHERE, o, d, xtol=1e-13, step=0.01)
    from impls.core.table import METHOD_TABLE

    eager = METHOD_TABLE["march_newton"](b, SPHERE, jnp.asarray(o), jnp.asarray(d), t_min=0.0, t_max=10.0, t_hit=None,
                                          **METHODS["march_newton"].validate(dict(xtol=1e-13, step=0.01)))
    np.testing.assert_array_equal(np.asarray(eager["status"]), jitted.status)
    np.testing.assert_allclose(np.asarray(eager["t"]), jitted.t, rtol=1e-14)


def test_bad_knobs_name_the_knob(any_backend):
    for method in ("sphere_trace", "march_bisect"):
        skip_unless_offered(any_backend, method)
    o, d = camera(2)
    with pytest.raises(ValueError, match="omega"):
        any_backend.prepare("sphere_trace", SPHERE, o, d, omega=2.5)
    with pytest.raises(ValueError, match="step"):
        any_backend.prepare("march_bisect", SPHERE, o, d, step=0.0)
    with pytest.raises(ValueError, match="unknown knob"):
        any_backend.prepare("march_bisect", SPHERE, o, d, tol=1e-3)


