"""Error statistics: each column checked against a value computed by hand."""

from __future__ import annotations

import numpy as np
import pytest

from bench.run.metrics import Quantity, _per_ray, depth_errors, error_stats
from bench.report.plots import fit_rate, pareto_front
from impls.protocol import RayResult, Status


def result(t, status):
    n = len(t)
    return RayResult(t=np.asarray(t, float), status=np.asarray(status, np.int32), iterations=np.zeros(n, np.int32),
                     evals=np.ones(n, np.int32))


def test_depth_errors_make_false_hits_and_misses_infinite():
    exact = np.array([1.0, np.inf, 2.0, np.inf])
    res = result([1.0 + 1e-9, 3.0, 5.0, np.inf], [Status.CONVERGED, Status.CONVERGED, Status.MAX_ITER, Status.MISS])
    e = depth_errors(res, exact)
    assert e[0] == pytest.approx(1e-9, rel=1e-6)
    assert e[1] == np.inf  # false hit
    assert e[2] == np.inf  # budget ran out: a false miss, whatever the iterate
    assert e[3] == 0.0  # both miss


def test_relative_and_ulp_errors():
    mag = np.array([1.0, 4.0, 0.0])
    e = np.array([2.0 ** -52, 2.0 ** -50, 0.0])
    s = error_stats(e, mag, "float64")
    assert s["error_ulps_max"] == pytest.approx(1.0)  # 1 ulp at 1 and at 4 (ulp(4) = 2^-50)
    assert s["error_rel_max"] == pytest.approx(2.0 ** -52)
    s32 = error_stats(np.array([2.0 ** -23]), np.array([1.0]), "float32")
    assert s32["error_ulps_max"] == pytest.approx(1.0) and s32["error_max_eps"] == pytest.approx(1.0)
    assert np.isnan(error_stats(np.zeros(0), np.zeros(0), "float64")["error_max"])
    big = error_stats(np.array([1.0, np.inf]), np.array([1.0, 1.0]), "float64")
    assert big["error_max"] == np.inf and big["error_max_finite"] == 1.0


def test_normal_angle_is_the_rotation_angle_even_when_tiny():
    rng = np.random.default_rng(0)
    n = rng.standard_normal((50, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    ax = np.cross(n, [0.0, 0.0, 1.0])
    ax /= np.linalg.norm(ax, axis=1, keepdims=True)
    for ang in (1e-12, 1e-6, 0.5, 3.0):
        got = n * np.cos(ang) + np.cross(ax, n) * np.sin(ang)
        e, _ = _per_ray(Quantity("normal_angle", "rad", got, n, np.ones(50, bool), angle=True))
        assert np.allclose(e, ang, rtol=1e-6, atol=1e-15)
    nan_out = n.copy()
    nan_out[3] = np.nan
    e, _ = _per_ray(Quantity("normal_angle", "rad", nan_out, n, np.ones(50, bool), angle=True))
    assert e[3] == np.inf and np.all(e[:3] < 1e-15)


def test_a_normal_that_is_not_unit_is_wrong_whatever_its_direction():
    """The angle atan2(|n × n*|, n·n*) is 0 for n = 0 and for any multiple of n*: a backend
    returning zero or unnormalised normals scored a perfect 0 and was picked.  A normal's error
    is also its length's distance from 1."""
    n = np.array([[0.0, 0.0, 1.0], [0.6, 0.8, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    got = np.array([[0.0, 0.0, 0.0], 3.0 * n[1], 1e-9 * n[2], n[3]])
    e, _ = _per_ray(Quantity("normal_angle", "rad", got, n, np.ones(4, bool), angle=True))
    assert e[0] == 1.0 and e[1] == pytest.approx(2.0) and e[2] == pytest.approx(1.0) and e[3] == 0.0


def test_a_root_finders_uncertified_misses_are_declined_rays_not_answers():
    """A miss the method did not certify (UNCERTIFIED, MAX_ITER on a ray that misses) has error 0
    (neither calls a hit) but answers nothing: ``n_declined`` counts it with the flagged hits, so
    that a root finder that never certifies a miss is not read as answering every ray."""
    from types import SimpleNamespace

    from bench.run.metrics import root_metrics

    case = SimpleNamespace(exact_t=np.array([1.0, np.inf, np.inf, 2.0, np.inf]), judged_mask=None,
                           exact_t_error_bounds=None)
    res = result([1.0, np.inf, 3.0, 9.0, np.inf],
                 [Status.CONVERGED, Status.UNCERTIFIED, Status.MAX_ITER, Status.UNCERTIFIED, Status.MISS])
    row = root_metrics(res, case, "float64", {}, {})[0]
    assert row["n_declined"] == 3 and row["n_miss_declined"] == 1 and row["n_false_miss"] == 1
    assert row["error_max_finite"] == 0.0  # the misses' errors are 0: only the count shows them


def test_fit_rate_recovers_known_orders_and_stops_at_the_floor():
    x = 2.0 ** np.arange(1, 9)
    for p in (0.5, 1.0, 2.0):
        assert fit_rate(x, 7 * x ** -p) == pytest.approx(p, rel=1e-9)
    floored = np.maximum(x ** -2.0, 1e-3)
    assert fit_rate(x, floored) == pytest.approx(2.0, abs=0.3)
    assert np.isnan(fit_rate(x[:2], x[:2] ** -1.0))


def test_pareto_front():
    t = np.array([1.0, 2.0, 3.0, 0.5, 2.5])
    e = np.array([1e-2, 1e-4, 1e-3, 1e-1, 1e-6])
    assert list(pareto_front(t, e)) == [3, 0, 1, 4]


def test_surface_colour_counts_the_background_at_misses():
    """``color_vs_surface`` compares with the surface-rendered image: ρ(x*) where the exact answer
    hits, the background 0 where it misses.  A renderer that paints a missing ray is off by that
    colour (it used to be judged on the hits only, so it passed), and a case whose every ray
    misses is checked on every ray (it read 'none reached': nothing was checked)."""
    from bench.run.metrics import render_metrics
    from impls.methods import get_method
    from reference import Case, Sphere, rays

    o, d = rays.pinhole(eye=(0, 0, 3), look_at=(0, 0, 0), fov_deg=60, width=8, height=8)
    spec = get_method("render_surface")
    for scene, some_hit in ((Sphere(), True), (Sphere(center=(5.0, 0.0, 0.0), radius=0.5), False)):
        case = Case(id="c", scene=scene, origins=o, directions=d, t_min=0.0, t_max=6.0)
        hit = case.hit_mask
        good = np.where(hit[:, None], np.nan_to_num(case.exact_surface_colors), 0.0)
        st = np.where(hit, Status.CONVERGED, Status.MISS).astype(np.int32)

        def row(color):
            res = RayResult(t=case.exact_t, status=st, iterations=np.ones(64, np.int32), evals=np.ones(64, np.int32),
                            outputs={"color": color})
            (r,) = [r for r in render_metrics(res, case, "float64", {}, {}, spec) if r["quantity"] == "color_vs_surface"]
            return r

        assert hit.any() == some_hit and (~hit).any()
        r = row(good)
        assert r["n_checked"] == 64 and r["error_max"] == 0.0  # every ray checked, the all-miss case too
        painted = good.copy()
        painted[~hit] = 0.25  # a halo on every missing ray
        assert row(painted)["error_max"] == pytest.approx(0.25 * np.sqrt(3))
