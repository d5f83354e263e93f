"""Status values exactly as the README's table says, on every backend (issue 33, finding 7).

The table ("Values by status, the same on every backend"): CONVERGED — finite outputs; MISS —
``t = inf``, colour and opacity 0; BAD_INPUT, NON_FINITE, LIPSCHITZ_VIOLATED — every float
output NaN (``t`` included); MAX_ITER — ``t`` the last iterate, other outputs NaN;
UNCERTIFIED — ``t`` inf or a depth, other outputs NaN; ILL_CONDITIONED — the value.
:func:`violations` checks it ray by ray on what any method of any
backend returns; the tests feed it the hostile inputs that broke it:

* a field that is NaN along the whole ray (every method family): the answer is NON_FINITE, never
  a MISS (before: the point-wise methods, given the NaN depth a root finder reports for it, said
  MISS with ``t = NaN``, and NON_FINITE with ``t = t_hit``);
* rays that meet no surface, with no ray bound and ``t_max = inf``: a MISS (``t = inf``),
  MAX_ITER or (a certified method whose steps near the surface were not all covered)
  UNCERTIFIED, never NON_FINITE: where |x|² overflows and φ becomes +inf on a search with no
  end, the ray has left every finite depth.
"""

from __future__ import annotations

import dataclasses
import math
import warnings

import numpy as np
import pytest

from impls import METHODS, Status
from reference import CallableField, Sphere
from reference.rays import normalize
from reference.rendering import SineColor
from reference.scene import Field, SceneInfo
from tests.conftest import BACKEND_IDS, resolve_or_skip

#: outputs that count samples, not values (volume renderers): exempt from "every float NaN"
COUNTS = ("samples_used", "work_saved")
N = 4
ROOTS = [m for m, s in METHODS.items() if s.family == "root"]
POINTWISE = [m for m, s in METHODS.items() if s.needs_t_hit and s.family in ("gradient", "param_grad")]
RENDER = ["render_surface", "volume_nerf_uniform", "volume_nerf_band"]


def _rows(a: np.ndarray, pred) -> np.ndarray:
    """``pred`` over every value of each ray's row (leading axis)."""
    a = np.asarray(a, np.float64).reshape(a.shape[0], -1)
    return np.all(pred(a), axis=1)


def violations(r, outputs: tuple[str, ...]) -> list[str]:
    """The rays of result ``r`` whose values contradict their status (README's table), one line
    per (status, what is wrong) with the count and the first offending values."""
    t = np.asarray(r.t, np.float64)
    st = np.asarray(r.status).astype(int)
    outs = {k: np.asarray(v) for k, v in (r.outputs or {}).items() if k in outputs and k not in COUNTS}
    bad: list[str] = []

    def check(status: Status, ok: np.ndarray, what: str):
        wrong = (st == int(status)) & ~ok
        if wrong.any():
            i = int(np.flatnonzero(wrong)[0])
            bad.append(f"{status.name}: {int(wrong.sum())} rays {what} (first: t={t[i]!r}, "
                       f"{ {k: np.asarray(v[i]).tolist() for k, v in outs.items()} })")

    nan = lambda a: _rows(a, np.isnan)  # noqa: E731
    check(Status.CONVERGED, np.isfinite(t) & np.all([_rows(v, np.isfinite) for v in outs.values()] or [True], axis=0),
          "have a non-finite t or output")
    check(Status.MISS, t == np.inf, "do not have t = inf")
    for k in ("color", "opacity"):
        if k in outs:
            check(Status.MISS, _rows(outs[k], lambda a: a == 0), f"do not have {k} 0")
    for s in (Status.NON_FINITE, Status.BAD_INPUT, Status.LIPSCHITZ_VIOLATED):
        check(s, np.isnan(t) & np.all([nan(v) for v in outs.values()] or [True], axis=0),
              "have a t or output that is not NaN")
    check(Status.MAX_ITER, np.all([nan(v) for v in outs.values()] or [True], axis=0), "have an output that is not NaN")
    check(Status.UNCERTIFIED, ~np.isnan(t) & (t != -np.inf) & np.all([nan(v) for v in outs.values()] or [True], axis=0),
          "have a NaN or -inf t, or an output that is not NaN")
    known = {int(s) for s in Status if s != Status.IN_PROGRESS}
    if not set(st.tolist()) <= known:
        bad.append(f"status codes {sorted(set(st.tolist()) - known)} are not impls.Status values")
    return bad


def _run(backend, method, scene, o, d, *, t_min=0.0, t_max=10.0, t_hit=None, dtype="float64", **knobs):
    spec = METHODS[method]
    extra = {"color": SineColor()} if getattr(spec, "needs_color", False) else {}
    if spec.needs_t_hit:
        extra["t_hit"] = np.full(o.shape[0], 2.0) if t_hit is None else t_hit
    if method not in backend.methods():
        pytest.skip(f"{backend.id} does not implement {method}")
    if dtype not in backend.capabilities.dtypes:
        pytest.skip(f"{backend.id} does not support {dtype}")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        p = backend.prepare(method, scene, o, d, dtype=dtype, t_min=t_min, t_max=t_max, **extra, **knobs)
        return p.result(p.run())


# -- scenes ------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class NaNBall(Field):
    """A smooth-declared field that is NaN everywhere (a user's field gone wrong: 0/0 in every
    point): point-wise methods and dt/dθ accept it, as they accept any smooth scene."""

    radius: float = 1.0
    kind = "nan_ball"

    def own_params(self):
        return {"radius": np.array(self.radius)}

    @property
    def info(self):
        return SceneInfo(exact_sdf=False, lipschitz=1.0, distance_bound=True, smooth=True, exact_hits=False,
                         exact_normals=False, exact_curvature=False, exact_hit_param_grad=False)

    def bounding_sphere(self):
        return None

    def _eval(self, x, xp, cursor):
        r = cursor.take(self.own_params()["radius"])
        return (xp.sqrt(xp.sum(x * x, axis=-1)) - r) * math.nan


def nan_field(x, xp):
    return xp.sum(x * x, axis=-1) * math.nan


def ball(x, xp):
    """|x| − 1 with no ray bound stated: a ray that misses it goes on for ever."""
    return xp.sqrt(xp.sum(x * x, axis=-1)) - 1.0


def rays_at_origin_ball(n=N):
    o = np.zeros((n, 3))
    o[:, 2] = -3.0
    o[:, 0] = np.linspace(-0.2, 0.2, n)
    return o, normalize(np.tile([[0.0, 0.0, 1.0]], (n, 1)))


def rays_missing_ball(n=N):
    o = np.zeros((n, 3))
    o[:, 0] = 3.0
    o[:, 1] = np.linspace(-0.1, 0.1, n)
    return o, normalize(np.tile([[1.0, 0.3, 0.2]], (n, 1)))


NAN_FIELD = CallableField(nan_field, lipschitz=1.0, name="tests.status_contract.nan_field")
UNBOUNDED_BALL = CallableField(ball, lipschitz=1.0, exact_sdf=True, name="tests.status_contract.ball")


# -- the field is NaN along the whole ray --------------------------------------------------------


@pytest.mark.parametrize("method", ROOTS + RENDER)
@pytest.mark.parametrize("t_max", [10.0, math.inf], ids=["t_max=10", "t_max=inf"])
@pytest.mark.parametrize("bid", BACKEND_IDS)
def test_a_nan_field_is_non_finite_never_a_miss(bid, method, t_max):
    if t_max == math.inf and METHODS[method].family == "render" and method != "render_surface":
        pytest.skip("volume rendering needs a finite t_max (refused with a ValueError)")
    o, d = rays_at_origin_ball()
    r = _run(resolve_or_skip(bid), method, NAN_FIELD, o, d, t_max=t_max, t_hit=np.full(N, 2.0))
    assert violations(r, METHODS[method].outputs) == []
    st = np.asarray(r.status)
    assert np.all(st == int(Status.NON_FINITE)), [Status(int(s)).name for s in st]


@pytest.mark.parametrize("method", POINTWISE)
@pytest.mark.parametrize("bid", BACKEND_IDS)
def test_pointwise_methods_map_depths_as_root_finders_report_them(bid, method):
    """The point-wise methods take a depth; given what a root finder reports — a depth, +inf for
    a MISS, NaN for NON_FINITE — they answer CONVERGED, MISS (t = inf) and NON_FINITE (t = NaN).
    Before: a NaN depth (a field NaN along the ray) gave MISS with t = NaN."""
    o, d = rays_at_origin_ball()
    t_hit = np.array([2.0, math.inf, math.nan, -math.inf])
    r = _run(resolve_or_skip(bid), method, Sphere(center=(0.0, 0.0, 0.0), radius=1.0), o, d, t_hit=t_hit)
    assert violations(r, METHODS[method].outputs) == []
    assert [Status(int(s)).name for s in np.asarray(r.status)] == ["CONVERGED", "MISS", "NON_FINITE", "NON_FINITE"]


@pytest.mark.parametrize("bid", BACKEND_IDS)
def test_the_band_renderers_map_depths_as_root_finders_report_them(bid):
    """``volume_*_band`` takes a depth too: +inf is a MISS (colour 0, the background), NaN and −inf
    NON_FINITE (colour NaN).  Before: every non-finite depth was a MISS, so a ray whose root finder
    met a NaN field was drawn as background (found by the 2026-11-30 renderer probe)."""
    o, d = rays_at_origin_ball()
    t_hit = np.array([2.0, math.inf, math.nan, -math.inf])
    r = _run(resolve_or_skip(bid), "volume_nerf_band", Sphere(center=(0.0, 0.0, 0.0), radius=1.0), o, d,
             t_max=6.0, t_hit=t_hit)
    assert violations(r, METHODS["volume_nerf_band"].outputs) == []
    assert [Status(int(s)).name for s in np.asarray(r.status)] == ["CONVERGED", "MISS", "NON_FINITE", "NON_FINITE"]
    color = np.asarray(r.outputs["color"])
    assert np.all(color[1] == 0) and np.all(np.isnan(color[2:]))


@pytest.mark.parametrize("bid", BACKEND_IDS)
def test_a_band_around_a_depth_outside_the_interval_is_bad_input(bid):
    """A finite t_hit before t_min or after t_max is no hit of the ray's interval: BAD_INPUT with
    colour NaN.  Before: CONVERGED, its band [t_hit − Δ, t_hit + Δ] clipped below at t_min only, so
    bins of negative width (t_hit = −1: colour 0.0 reported as a converged render).  A hit within Δ
    of t_max gets a band clipped at t_max, the end of the integral it stands for."""
    o, d = rays_at_origin_ball()
    sphere = Sphere(center=(0.0, 0.0, 0.0), radius=1.0)
    r = _run(resolve_or_skip(bid), "volume_nerf_band", sphere, o, d, t_min=0.5, t_max=6.0,
             t_hit=np.array([-1.0, 0.25, 6.5, 2.0]))
    assert violations(r, METHODS["volume_nerf_band"].outputs) == []
    assert [Status(int(s)).name for s in np.asarray(r.status)] == ["BAD_INPUT"] * 3 + ["CONVERGED"]
    assert np.all(np.isnan(np.asarray(r.outputs["color"])[:3]))
    near_end = _run(resolve_or_skip(bid), "volume_nerf_band", sphere, o, d, t_min=0.5, t_max=2.05,
                    t_hit=np.full(N, 2.0))
    assert np.all(np.asarray(near_end.status) == int(Status.CONVERGED))
    edges = np.asarray(near_end.outputs["color"])
    assert np.all(np.isfinite(edges)) and np.all(edges >= 0) and np.all(edges <= 1)


@pytest.mark.parametrize("method", POINTWISE)
@pytest.mark.parametrize("bid", BACKEND_IDS)
def test_pointwise_methods_on_a_nan_field_are_non_finite_with_t_nan(bid, method):
    """A finite depth on a field whose gradient is NaN: NON_FINITE with t NaN (before: NON_FINITE
    with t = t_hit, and for dt/dθ ILL_CONDITIONED carrying a NaN "value")."""
    o, d = rays_at_origin_ball()
    r = _run(resolve_or_skip(bid), method, NaNBall(), o, d, t_hit=np.full(N, 2.0))
    assert violations(r, METHODS[method].outputs) == []
    assert np.all(np.asarray(r.status) == int(Status.NON_FINITE)), [Status(int(s)).name for s in np.asarray(r.status)]


# -- no surface, no bound -------------------------------------------------------------------------

@pytest.mark.parametrize("dtype", ["float64", "float32"])
@pytest.mark.parametrize("method", ROOTS)
@pytest.mark.parametrize("bid", BACKEND_IDS)
def test_rays_with_no_surface_and_no_bound_are_a_miss_or_max_iter(bid, method, dtype):
    o, d = rays_missing_ball()
    # a constant-step marcher never reaches t = inf here (Δ per step): every ray ends MAX_ITER
    # whatever the budget, so 256 steps (ladder steps from the 64th on) check what 4096 would, in
    # a sixteenth of the per-step overhead (torch: 6.7 s a test at 4096)
    budget = {"max_steps": 256} if any(k.name == "step" for k in METHODS[method].knobs) else {}
    r = _run(resolve_or_skip(bid), method, UNBOUNDED_BALL, o, d, t_max=math.inf, dtype=dtype, **budget)
    assert violations(r, METHODS[method].outputs) == []
    names = {Status(int(s)).name for s in np.asarray(r.status)}
    assert names <= {"MISS", "MAX_ITER", "UNCERTIFIED"}, names


@pytest.mark.parametrize("dtype", ["float64", "float32"])
@pytest.mark.parametrize("method", ROOTS)
@pytest.mark.parametrize("bid", BACKEND_IDS)
def test_rays_past_a_bounded_scene_with_t_max_inf_are_a_miss(bid, method, dtype):
    """The same rays past a scene that states its ray bound (every backend compiles a Sphere):
    the search ends at the bound, a MISS with t = inf."""
    o, d = rays_missing_ball()
    r = _run(resolve_or_skip(bid), method, Sphere(center=(0.0, 0.0, 0.0), radius=1.0), o, d, t_max=math.inf,
             dtype=dtype)
    assert violations(r, METHODS[method].outputs) == []
    assert np.all(np.asarray(r.status) == int(Status.MISS)), [Status(int(s)).name for s in np.asarray(r.status)]


def test_the_checker_sees_each_kind_of_violation():
    """:func:`violations` is what the tests above rest on: it must fail on each breach."""
    from impls.protocol import RayResult

    def res(t, status, **outs):
        n = len(t)
        return RayResult(t=np.array(t, float), status=np.array(status), iterations=np.zeros(n, int),
                         evals=np.zeros(n, int), outputs={k: np.array(v, float) for k, v in outs.items()})

    M, NF, C, MX = int(Status.MISS), int(Status.NON_FINITE), int(Status.CONVERGED), int(Status.MAX_ITER)
    assert violations(res([math.inf, math.nan, 1.0, 3.0], [M, NF, C, MX], color=[[0] * 3, [math.nan] * 3,
                                                                                [1] * 3, [math.nan] * 3]),
                      ("color",)) == []
    assert "MISS" in violations(res([math.nan], [M]), ())[0]
    assert "MISS" in violations(res([math.inf], [M], color=[[0, 0.5, 0]]), ("color",))[0]
    assert "NON_FINITE" in violations(res([2.0], [NF]), ())[0]
    assert "NON_FINITE" in violations(res([math.nan], [NF], normal=[[0, 0, 1]]), ("normal",))[0]
    assert "CONVERGED" in violations(res([math.inf], [C]), ())[0]
    assert "MAX_ITER" in violations(res([1.0], [MX], normal=[[0, 0, 1]]), ("normal",))[0]
    assert "not impls.Status" in violations(res([1.0], [7]), ())[0]


@pytest.mark.parametrize("bid", ["numpy", "torch:cpu", pytest.param("jax:cpu", marks=pytest.mark.slow)])
@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_no_certified_miss_when_the_surface_passes_through_t_max(bid, dtype):
    """φ = z (a user's field), rays straight down from z = 3 with t_max = 3: φ = 0 exactly at the
    range's end, the surface through t_max.  The spheres certify [t_min, t_max) free of surface,
    not t_max itself, and sphere tracing called these rays certified MISSes; now UNCERTIFIED (the
    hybrids and the marches already were)."""
    be = resolve_or_skip(bid)
    scene = CallableField(lambda x, xp: x[..., 2] * 1.0, lipschitz=1.0, name="plane.through.tmax")
    o = np.array([[0.0, 0.0, 3.0], [0.25, -0.5, 3.0]])
    d = np.array([[0.0, 0.0, -1.0]] * 2)
    for method in ("sphere_trace", "hybrid_secant"):
        p = be.prepare(method, scene, o, d, dtype=dtype, t_min=0.0, t_max=3.0)
        status = np.asarray(p.result(p.run()).status)
        assert not np.any(status == int(Status.MISS)), (method, [Status(int(s)).name for s in status])
