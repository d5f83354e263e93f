"""The bad-input suite: malformed input at the public entry points ``backend.prepare(...).run()``
/ ``.result()`` ends in a clear error naming the argument or in flagged per-ray statuses.

Property asserted for every input (``outcome``): either a ValueError/TypeError whose message
names the offending argument, or a result in which every ray with a non-finite ``t`` has a
non-CONVERGED status and every CONVERGED ray has finite outputs — never a silent NaN, never an
IndexError/RuntimeError/OverflowError from deep inside.

Categories and their handling (numpy always; torch and jax where noted):

* rays — NaN/inf components, zero directions: per-ray BAD_INPUT, every float output NaN;
  huge components (1e300): a result (overflow gives NON_FINITE or MISS, never a CONVERGED NaN);
  non-unit directions: ValueError naming ``directions`` with the worst ray's ‖d‖ − 1 and the fix;
  float32 directions normalised in float32: accepted (the unit test scales with the dtype),
  all backends and both run dtypes;
  wrong shapes, zero rays, mismatched origin/direction counts: ValueError naming
  ``origins``/``directions``; int dtype: accepted (exact); complex, bool, object, ragged:
  TypeError naming the argument.
* depth range — t_min > t_max, NaN, −inf t_min, bool, str: ValueError/TypeError naming
  ``t_min``/``t_max``; t_hit of the wrong shape or dtype: naming ``t_hit``; t_hit for a method
  that finds its own depths: ValueError naming ``t_hit``.
* knobs — wrong type (str, None, bool: ``max_steps=True`` is not 1), NaN, ±inf, negative, out of
  range, non-integral for an integer knob, beyond int32: TypeError/ValueError naming the method,
  the knob and its valid range; unknown knobs: ValueError listing the valid ones.
* methods and dtypes — unknown or non-string method: naming ``method``; dtype strings not
  supported ("float16", "int32"), non-strings (np.float32, None): ValueError naming ``dtype``;
  a scene that is not a Field: TypeError naming ``scene``.
* user fields (numpy, torch, jax at fixed shapes) — wrong shape ((…, 1), a slice, an extra
  axis), a Python scalar, a 0-d array, integer or complex dtype, numpy arrays for torch/jax
  points, an exception raised inside: FieldError (a ValueError) naming the field and stating what
  it returned against what was expected; NaN everywhere: NON_FINITE per ray (+inf everywhere
  is empty space: MISS, transparent).
* cameras — ``reference.rays.pinhole`` with eye == look_at, up zero or parallel to the view,
  non-finite vectors, a field of view outside (0, 180): ValueError naming the argument.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from impls import registry
from impls.methods import METHODS
from impls.protocol import Status
from reference import Sphere
from reference.numerical import CallableField
from reference.rays import impact, pinhole
from reference.scene import FieldError, check_field_output

SPHERE = Sphere((0.0, 0.0, 0.0), 1.0)
SETTINGS = settings(max_examples=30, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
CONV = int(Status.CONVERGED)
#: one method per family and code path (root finders, point-wise, dt/dθ, both renderers)
SMALL_METHODS = ("sphere_trace", "march_bisect", "hybrid_secant", "normal", "dt_implicit", "dt_unrolled",
                 "render_surface", "volume_nerf_uniform", "volume_neus_band")


def _backend(bid):
    b, reasons = registry.available([bid])
    if not b:
        pytest.skip(f"{bid} unavailable: {reasons}")
    return b[0]


@pytest.fixture(scope="module")
def numpy_backend():
    return _backend("numpy")


def good_rays(n=4):
    o, d = pinhole((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), width=n, height=1, fov_deg=30.0)
    return o, d


def call(backend, method, scene, o, d, **kw):
    """prepare + run + result; ``t_hit`` and a finite ``t_max`` supplied where the method needs them."""
    spec = METHODS.get(method) if isinstance(method, str) else None
    kw.setdefault("t_max", 6.0)
    if spec is not None and spec.needs_t_hit and "t_hit" not in kw:
        kw["t_hit"] = np.full(np.shape(o)[0] if np.ndim(o) == 2 else 1, 2.0)
    if spec is not None and "n_samples" in {k.name for k in spec.knobs}:
        kw.setdefault("n_samples", 8)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        p = backend.prepare(method, scene, o, d, **kw)
        return p.result(p.run())


def check_result(r):
    """No silent NaN, no CONVERGED non-finite output."""
    conv = r.status == CONV
    assert not np.any(~np.isfinite(r.t) & conv), (r.t, r.status)
    for k, v in r.outputs.items():
        v = np.asarray(v)
        if v.dtype.kind == "f":
            fin = np.isfinite(v) if v.ndim == 1 else np.all(np.isfinite(v.reshape(len(v), -1)), axis=1)
            assert np.all(fin[conv]), (k, v, r.status)
    assert set(np.unique(r.status).tolist()) <= {int(s) for s in Status if s != Status.IN_PROGRESS}


def outcome(fn, names):
    """Run ``fn``: a ValueError/TypeError must name one of ``names``; a result must be flagged
    honestly.  Any other exception fails the test (it propagates)."""
    try:
        r = fn()
    except (ValueError, TypeError) as e:
        msg = str(e)
        assert any(n in msg for n in names), f"{type(e).__name__} does not name any of {names}: {msg}"
        return e
    check_result(r)
    return r


# -- finding 2: a user field of the wrong shape is never broadcast silently ------------------------

BACKENDS = ["numpy", "torch:cpu", "jax:cpu"]


@pytest.mark.parametrize("bid", BACKENDS)
@pytest.mark.parametrize("method", ["sphere_trace", "hybrid_secant"])
def test_field_of_wrong_shape_is_an_error_naming_it(bid, method):
    """The issue's field: (…, :1) made all 64 rays CONVERGED at ray 0's depth (numpy, torch)."""
    b = _backend(bid)
    f = CallableField(lambda x, xp: (xp.sqrt(xp.sum(x * x, axis=-1)) - 1)[..., :1], lipschitz=1.0, name="sliced")
    o, d = impact(64, np.linspace(0.0, 0.9, 64), 3.0, 0)
    with pytest.raises(FieldError, match=r"'sliced'.*returned shape \(1,\).*x\.shape\[:-1\] = \(64,\)"):
        call(b, method, f, o, d)


MALFORMED = {
    "scalar": (lambda x, xp: 1.0, "a scalar float"),
    "zero_d": (lambda x, xp: xp.sum(x * 0.0) + 1.0, r"returned shape \(\)"),
    "trailing_axis": (lambda x, xp: xp.sqrt(xp.sum(x * x, axis=-1, keepdims=True)) - 1, r"returned shape \(.*, 1\)"),
    "integer": (lambda x, xp: xp.astype(xp.sum(x * x, axis=-1) > 1.0, xp.int32), "dtype"),
    "complex": (lambda x, xp: xp.astype(xp.sqrt(xp.sum(x * x, axis=-1)) - 1, xp.complex128), "dtype"),
    "raises": (lambda x, xp: (_ for _ in ()).throw(KeyError("boom")), "raised KeyError"),
}


@pytest.mark.parametrize("bid", BACKENDS)
@pytest.mark.parametrize("kind", sorted(MALFORMED) + ["numpy_inside"])
def test_malformed_field_is_an_error_naming_it(bid, kind):
    b = _backend(bid)
    if kind == "numpy_inside":
        if bid == "numpy":
            pytest.skip("np.linalg.norm is the namespace here")
        fn, what = (lambda x, xp: np.linalg.norm(x, axis=-1) - 1.0), "numpy|raised"
    else:
        fn, what = MALFORMED[kind]
    f = CallableField(fn, lipschitz=1.0, name=f"user_{kind}")
    o, d = good_rays(4)
    for method in ("sphere_trace", "march_newton"):
        with pytest.raises(FieldError, match=f"'user_{kind}'") as info:
            call(b, method, f, o, d)
        assert "rootfind" not in str(info.value)
        assert any(w in str(info.value) for w in what.split("|")) or info.match(what)


def test_nested_callable_field_is_checked():
    from reference import Union

    bad = CallableField(lambda x, xp: xp.sum(x, axis=-1, keepdims=True), lipschitz=2.0, name="inner")
    with pytest.raises(FieldError, match="'inner'"):
        Union(SPHERE, bad).value(np.zeros((5, 3)))


def test_valid_field_output_passes_through_unchanged():
    """The check costs no pass over the data: a valid φ is returned as the same object; another
    floating precision is converted to the points' dtype."""
    x = np.zeros((7, 3))
    phi = np.ones(7)
    assert check_field_output(SPHERE, x, phi) is phi
    out = check_field_output(SPHERE, x.astype(np.float32), phi)
    assert out.dtype == np.float32 and out.shape == (7,)


# -- finding 9: float32 rays -----------------------------------------------------------------------


@pytest.mark.parametrize("bid", BACKENDS)
@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_float32_normalised_directions_are_accepted(bid, dtype):
    b = _backend(bid)
    rng = np.random.default_rng(5)
    target = rng.uniform(-0.5, 0.5, (64, 3)).astype(np.float32)
    o = np.tile(np.float32([0.0, 0.0, 3.0]), (64, 1))
    d = target - o
    d = d / np.linalg.norm(d, axis=1, keepdims=True)  # in float32: ‖d‖ − 1 up to a few 1e-8
    assert d.dtype == np.float32
    assert np.abs(np.linalg.norm(d.astype(np.float64), axis=1) - 1).max() > 1e-12  # the old test's threshold
    kw = {"xtol": 1e-5} if dtype == "float32" else {}
    r = call(b, "hybrid_secant", SPHERE, o, d, dtype=dtype, **kw)
    assert np.all(r.status == CONV)
    # the ray solved is (o, d / ‖d‖) normalised in float64 (impls.base.check_rays): t is a distance
    d64 = d.astype(np.float64)
    exact = SPHERE.first_hit(o.astype(np.float64), d64 / np.linalg.norm(d64, axis=1, keepdims=True), 0.0)
    assert np.abs(r.t - exact).max() < (1e-4 if dtype == "float32" else 1e-9)


@pytest.mark.parametrize("bid", BACKENDS)
@pytest.mark.parametrize("method", ["sphere_trace", "hybrid_secant"])
def test_float32_normalised_directions_do_not_step_across_a_thin_shell(bid, method):
    """A 1e-5 shell seen from 1,000 away along directions normalised in float32 (‖d‖ − 1 up to
    ±1e-7), solved in float64: a step φ/L along d moved ‖d‖·φ/L, 1e-4 past the nearest surface
    and across the shell, and 1,746 of 4,000 rays were CONVERGED on its far side (sphere tracing,
    numpy; 1,703 with hybrid_secant).  Normalised again in float64, none is."""
    from reference.csg import Difference
    from reference.primitives import Sphere

    b = _backend(bid)
    scene = Difference(Sphere(radius=1.0 + 1e-5), Sphere(radius=1.0))
    rng = np.random.default_rng(0)
    o = rng.normal(size=(4000, 3))
    o = 1000.0 * o / np.linalg.norm(o, axis=1, keepdims=True)
    d = (rng.uniform(-0.3, 0.3, (4000, 3)) - o).astype(np.float32)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    r = call(b, method, scene, o, d, t_max=2000.0)
    d64 = d.astype(np.float64)
    exact = scene.first_hit(o, d64 / np.linalg.norm(d64, axis=1, keepdims=True), 0.0)
    conv = r.status == CONV
    assert not np.any(conv & (np.abs(r.t - exact) > 1e-9 * exact)), int(np.sum(conv & (r.t > exact + 1e-9 * exact)))
    assert not np.any((r.status == Status.MISS) & np.isfinite(exact))


def test_non_unit_directions_say_how_far_and_how_to_fix(numpy_backend):
    o, d = good_rays(4)
    d = d.copy()
    d[2] *= 1 + 3e-6
    with pytest.raises(ValueError, match=r"directions.*ray 2.*3\.000e-06.*float64") as info:
        numpy_backend.prepare("sphere_trace", SPHERE, o, d)
    assert "np.linalg.norm" in str(info.value)
    # the same float32 error is inside float32's tolerance only when the arrays are float32
    with pytest.raises(ValueError, match="directions"):
        numpy_backend.prepare("sphere_trace", SPHERE, o, d * (1 + 2e-11))
    numpy_backend.prepare("sphere_trace", SPHERE, o.astype(np.float32), (d / np.linalg.norm(d, axis=1,
                                                                                          keepdims=True)).astype(np.float32))


# -- finding 11: knobs -----------------------------------------------------------------------------


@pytest.mark.parametrize("value", [True, False, np.bool_(True)])
def test_bool_is_not_a_step_count(numpy_backend, value):
    o, d = good_rays(2)
    with pytest.raises(TypeError, match=r"sphere_trace: knob max_steps=.*integer in \[1, "):
        numpy_backend.prepare("sphere_trace", SPHERE, o, d, max_steps=value)


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_non_finite_knobs_are_rejected(numpy_backend, value):
    o, d = good_rays(2)
    for method, knob in (("sphere_trace", "tol"), ("sphere_trace", "max_steps"), ("volume_nerf_uniform", "sharpness")):
        with pytest.raises(ValueError, match=f"{method}: knob {knob}=.*finite.*valid"):
            numpy_backend.prepare(method, SPHERE, o, d, t_max=6.0, **{knob: value})


@pytest.mark.parametrize("bid", ["numpy", "torch:cpu", "jax:cpu"])
@pytest.mark.parametrize("method", [m for m, s in METHODS.items() if s.family == "param_grad"])
def test_dt_dtheta_of_a_field_without_parameters_is_an_error_naming_them(bid, method):
    """dt/dθ of a field with no θ is refused by prepare, saying how a user's field takes θ.  Before:
    numpy's run raised numpy's own 'need at least one array to stack' (a user's CallableField without
    ``params``; the runner skipped such cases itself, a caller of the backend got the crash)."""
    backend = registry.resolve(bid)
    if isinstance(backend, registry.Unavailable):
        pytest.skip(backend.reason)
    f = CallableField(lambda x, xp: xp.sqrt(xp.sum(x * x, axis=-1)) - 1, lipschitz=1.0, name="plain", smooth=True)
    o, d = good_rays(2)
    hits = {"t_hit": np.full(2, 2.0)} if METHODS[method].needs_t_hit else {}
    with pytest.raises(ValueError, match=r"parameters θ.*none.*params=θ"):
        backend.prepare(method, f, o, d, t_max=6.0, **hits)


@pytest.mark.parametrize("method, knob, value", [("volume_nerf_uniform", "n_samples", 10**9),
                                                 ("volume_neus_importance", "n_samples", 2**16 + 1),
                                                 ("volume_nerf_importance", "n_coarse", 10**6)])
def test_sample_counts_beyond_one_rays_memory_are_rejected(numpy_backend, method, knob, value):
    """A sample count whose single ray does not fit in memory is an error naming the knob and its
    range, raised by prepare (before any allocation): 1e9 samples a ray ran out of memory."""
    o, d = good_rays(2)
    with pytest.raises(ValueError, match=rf"{method}: knob {knob}={value}.*out of range.*\[1, \d+\]"):
        numpy_backend.prepare(method, SPHERE, o, d, t_max=6.0, **{knob: value})


# -- finding 10 (cameras) ----------------------------------------------------------------------------


@pytest.mark.parametrize("kw, name", [
    (dict(eye=(1.0, 2.0, 3.0), look_at=(1.0, 2.0, 3.0)), "look_at"),
    (dict(eye=(0.0, 3.0, 0.0), look_at=(0.0, 0.0, 0.0)), "up"),
    (dict(eye=(0.0, 0.0, 3.0), look_at=(0.0, 0.0, 0.0), up=(0.0, 0.0, 2.0)), "up"),
    (dict(eye=(0.0, 0.0, 3.0), look_at=(0.0, 0.0, 0.0), up=(0.0, 0.0, 0.0)), "up"),
    (dict(eye=(0.0, 0.0, np.nan), look_at=(0.0, 0.0, 0.0)), "eye"),
    (dict(eye=(0.0, 0.0, 3.0), look_at=(0.0, 0.0, 0.0), fov_deg=180.0), "fov_deg"),
    (dict(eye=(0.0, 0.0, 3.0), look_at=(0.0, 0.0, 0.0), width=0), "width"),
])
def test_undefined_camera_is_an_error_naming_the_argument(kw, name):
    with pytest.raises(ValueError, match=f"pinhole: {name}"):
        pinhole(**kw)


def test_pinhole_still_gives_unit_directions():
    o, d = pinhole((0.3, -2.0, 3.0), (0.1, 0.2, 0.0), up=(0.0, 0.0, 1.0), width=5, height=3)
    assert np.all(np.isfinite(d)) and np.abs(np.linalg.norm(d, axis=1) - 1).max() < 1e-15


# -- properties --------------------------------------------------------------------------------------

component = st.one_of(st.floats(-4.0, 4.0), st.sampled_from([math.nan, math.inf, -math.inf, 0.0, 1e300, -1e300, 1e-300]))


@st.composite
def ray_arrays(draw):
    n = draw(st.integers(1, 5))
    o = np.array(draw(st.lists(st.lists(component, min_size=3, max_size=3), min_size=n, max_size=n)))
    d = np.array(draw(st.lists(st.lists(component, min_size=3, max_size=3), min_size=n, max_size=n)))
    if draw(st.booleans()):  # mostly unit directions, so that the runs get past validation
        with np.errstate(all="ignore"):
            nrm = np.linalg.norm(d, axis=1, keepdims=True)
            d = np.where((nrm > 0) & np.isfinite(nrm), d / np.where(nrm > 0, nrm, 1.0), d)
    shape = draw(st.sampled_from(["ok", "ok", "ok", "ok", "short_o", "flat_d", "count", "empty", "4cols"]))
    if shape == "short_o":
        o = o[:, :2]
    elif shape == "flat_d":
        d = d.ravel()
    elif shape == "count":
        d = np.concatenate([d, d[:1]])
    elif shape == "empty":
        o, d = o[:0], d[:0]
    elif shape == "4cols":
        d = np.concatenate([d, d[:, :1]], axis=1)
    dt = draw(st.sampled_from(["keep", "keep", "keep", "float32", "int", "complex", "object", "bool", "list"]))
    if dt == "float32":
        o, d = o.astype(np.float32), d.astype(np.float32)
    elif dt == "int":
        with np.errstate(all="ignore"):
            d = np.nan_to_num(d).astype(np.int64)
    elif dt == "complex":
        d = d.astype(np.complex128)
    elif dt == "object":
        d = np.array([None] + [1.0] * (d.size - 1) if d.size else [None], dtype=object)
    elif dt == "bool":
        o = o.astype(bool)
    elif dt == "list":
        o = o.tolist()
    return o, d


@SETTINGS
@given(rays=ray_arrays(), method=st.sampled_from(SMALL_METHODS))
def test_malformed_rays(numpy_backend, rays, method):
    o, d = rays
    outcome(lambda: call(numpy_backend, method, SPHERE, o, d), ("origins", "directions", "t_hit"))


@SETTINGS
@given(rays=ray_arrays())
def test_malformed_rays_torch(rays):
    b = _backend("torch:cpu")
    o, d = rays
    outcome(lambda: call(b, "hybrid_secant", SPHERE, o, d), ("origins", "directions"))


@SETTINGS
@given(bad=st.lists(st.sampled_from(["nan_o", "inf_o", "zero_d", "nan_d", "inf_d", "ok"]), min_size=4, max_size=4),
       method=st.sampled_from(SMALL_METHODS))
@pytest.mark.slow  # compiles many kernels or sweeps a whole catalog
def test_flagged_rays_jax_fixed_shape(bad, method):
    """jax compiles per shape: 4 rays, the kind of each drawn."""
    b = _backend("jax:cpu")
    o, d = good_rays(4)
    o, d = o.copy(), d.copy()
    for i, k in enumerate(bad):
        if k == "nan_o":
            o[i, 0] = np.nan
        elif k == "inf_o":
            o[i, 2] = np.inf
        elif k == "zero_d":
            d[i] = 0.0
        elif k == "nan_d":
            d[i, 1] = np.nan
        elif k == "inf_d":
            d[i, 0] = -np.inf
    r = outcome(lambda: call(b, method, SPHERE, o, d), ())
    flagged = np.array([k != "ok" for k in bad])
    assert np.all(r.status[flagged] == Status.BAD_INPUT)
    assert np.all(r.status[~flagged] != Status.BAD_INPUT)


number = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-10, 10**12), st.booleans(),
                   st.none(), st.text(max_size=3), st.just(np.float32(0.5)), st.just(np.int64(3)))


@SETTINGS
@given(t_min=number, t_max=number)
def test_malformed_depth_range(numpy_backend, t_min, t_max):
    o, d = good_rays(2)
    outcome(lambda: call(numpy_backend, "sphere_trace", SPHERE, o, d, t_min=t_min, t_max=t_max), ("t_min", "t_max"))


@SETTINGS
# the methods numpy offers (not raycast, an engine's own query: MethodSpec.libs = ())
@given(method=st.sampled_from(sorted(m for m, s in METHODS.items() if s.libs is None or "numpy" in s.libs)),
       data=st.data())
def test_malformed_knobs(numpy_backend, method, data):
    spec = METHODS[method]
    names = [k.name for k in spec.knobs] + ["tolerance", "max_step", ""]
    name = data.draw(st.sampled_from(names))
    value = data.draw(number)
    o, d = good_rays(2)
    cheap = not (isinstance(value, (int, np.integer)) and not isinstance(value, bool) and value > 64) and not (
        isinstance(value, float) and name in ("extrapolate", "reach", "h", "delta", "overstep", "min_step", "step"))

    def go():
        kw = {name: value}
        p = numpy_backend.prepare(method, SPHERE, o, d, t_max=6.0,
                                  t_hit=np.full(2, 2.0) if spec.needs_t_hit else None, **kw)
        return p.result(p.run()) if cheap else None

    try:
        r = go()
    except (ValueError, TypeError) as e:
        msg = str(e)
        assert (name in msg and method in msg) or "unknown knob" in msg, msg
        if "unknown knob" not in msg:
            assert "valid:" in msg, msg
        return
    if r is not None:
        check_result(r)


@SETTINGS
@given(method=st.one_of(st.text(max_size=12), st.sampled_from(["sphere_trace", "normal", None, 3])),
       dtype=st.sampled_from(["float64", "float32", "float16", "int32", "", np.float32, None, 3]))
def test_unknown_methods_and_dtypes(numpy_backend, method, dtype):
    o, d = good_rays(2)
    outcome(lambda: call(numpy_backend, method, SPHERE, o, d, dtype=dtype), ("method", "dtype"))


def test_scene_that_is_not_a_field(numpy_backend):
    o, d = good_rays(2)
    with pytest.raises(TypeError, match="scene must be"):
        numpy_backend.prepare("march_bisect", lambda x, xp: x[..., 0], o, d)


@SETTINGS
@given(t_hit=st.one_of(st.just([2.0]), st.just(np.full(3, 2.0)), st.just(np.full(2, np.nan)),
                       st.just(np.full(2, 1j)), st.just("x"), st.just(np.full((2, 1), 2.0))),
       method=st.sampled_from(["normal", "dt_implicit", "volume_nerf_band", "sphere_trace"]))
def test_malformed_t_hit(numpy_backend, t_hit, method):
    o, d = good_rays(2)
    outcome(lambda: call(numpy_backend, method, SPHERE, o, d, t_hit=t_hit), ("t_hit",))


FIELD_KINDS = {
    "nan": lambda x, xp: xp.sum(x, axis=-1) * math.nan,
    "inf": lambda x, xp: xp.sum(x * 0.0, axis=-1) + math.inf,
    "slice": lambda x, xp: (xp.sqrt(xp.sum(x * x, axis=-1)) - 1)[..., :1],
    "extra_axis": lambda x, xp: xp.sqrt(x * x) - 1,
    "scalar": lambda x, xp: 0.5,
    "raises": lambda x, xp: 1 / 0,
    "numpy": lambda x, xp: np.sqrt(np.sum(np.asarray(x) ** 2, axis=-1)) - 1,
    "good": lambda x, xp: xp.sqrt(xp.sum(x * x, axis=-1)) - 1,
}


@SETTINGS
@given(kind=st.sampled_from(sorted(FIELD_KINDS)), method=st.sampled_from(SMALL_METHODS),
       bid=st.sampled_from(["numpy", "torch:cpu"]))
def test_malformed_fields(kind, method, bid):
    b = _backend(bid)
    f = CallableField(FIELD_KINDS[kind], lipschitz=1.0, name=f"field_{kind}")
    # 'smooth' is not stated by a CallableField: point-wise methods refuse it (naming the method)
    o, d = good_rays(3)
    r = outcome(lambda: call(b, method, f, o, d), (f"field_{kind}", method))
    if kind == "nan" and not isinstance(r, Exception):  # (φ = +inf is empty space: a valid, clear answer)
        assert not np.any(r.status == CONV)


@SETTINGS
@given(kind=st.sampled_from(sorted(FIELD_KINDS)), method=st.sampled_from(["sphere_trace", "volume_nerf_uniform"]))
def test_malformed_fields_jax(kind, method):
    b = _backend("jax:cpu")
    f = CallableField(FIELD_KINDS[kind], lipschitz=1.0, name=f"field_{kind}")
    o, d = good_rays(3)
    r = outcome(lambda: call(b, method, f, o, d), (f"field_{kind}",))
    if kind == "nan" and not isinstance(r, Exception):  # (φ = +inf is empty space: a valid, clear answer)
        assert not np.any(r.status == CONV)


@pytest.mark.parametrize("bid", BACKENDS)
def test_volume_rendering_refuses_an_infinite_t_max_at_prepare_and_bench_skips_it(bid):
    """A volume renderer samples all of [t_min, t_max]: t_max = inf is a ValueError naming t_max
    from ``prepare`` on every backend (numpy and torch raised it only in ``run``, which bench
    recorded as a failed configuration: 288 failed rows for one user case with a ground plane),
    and the planner skips such a configuration with the reason while the root finders run."""
    from bench.run.metrics import family_skip_reason
    from reference import Case, Plane

    b = _backend(bid)
    o, d = good_rays()
    for method in ("volume_nerf_uniform", "volume_neus_importance", "volume_volsdf_band"):
        kw = {"t_hit": np.full(4, 2.0)} if METHODS[method].needs_t_hit else {}
        with pytest.raises(ValueError, match="t_max"):
            b.prepare(method, Sphere(), o, d, t_min=0.0, t_max=math.inf, n_samples=8, **kw)
    po, pd_ = pinhole((0.0, -3.0, 1.0), (0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0), width=4, height=4, fov_deg=60.0)
    case = Case(id="user.plane.inf", scene=Plane(), origins=po, directions=pd_, t_min=0.0, t_max=math.inf)
    assert "t_max = inf" in family_skip_reason(METHODS["volume_nerf_uniform"], case)
    assert family_skip_reason(METHODS["hybrid_secant"], case) is None


class _OneChannel:
    def value(self, x, xp=np):
        return xp.sum(x, axis=-1)  # one value per point, not (r, g, b)


class _FourChannels:
    def value(self, x, xp=np):
        return xp.concat([x, x[..., :1]], axis=-1)


class _Grey32:
    def value(self, x, xp=np):
        return xp.astype(0.5 + 0.0 * x, xp.float32)  # another precision: converted, accepted


@pytest.mark.parametrize("bid", BACKENDS)
@pytest.mark.parametrize("method", ["render_surface", "volume_nerf_uniform"])
def test_a_colour_field_of_the_wrong_shape_is_an_error_naming_it(bid, method):
    """A user's colour field is checked on every output (reference.rendering.CheckedColor): one
    channel or four is a FieldError naming the colour field and the fix, on every backend (jax's
    volume renderer returned a (16, 64) 'colour', render_surface a (16, 4) one, numpy an AxisError
    that named nothing); a float32 field under a float64 run is converted and accepted; the same
    user field keeps one kernel (the wrapper is equal to, and hashes as, the field)."""
    from reference.rendering import CheckedColor
    from reference.scene import FieldError

    b = _backend(bid)
    o, d = good_rays()
    for bad in (_OneChannel(), _FourChannels()):
        with pytest.raises(FieldError, match=f"colour field {type(bad).__name__}.*returned shape"):
            call(b, method, Sphere(), o, d, color=bad)
    r = call(b, method, Sphere(), o, d, color=_Grey32())
    assert r.outputs["color"].shape == (4, 3) and np.all(np.isfinite(r.outputs["color"]))
    g = _Grey32()
    assert CheckedColor(g) == CheckedColor(g) and hash(CheckedColor(g)) == hash(CheckedColor(g))
