"""``march_chandrupatla``: isobench's march, then scipy's elementwise ``find_root`` on the brackets.

It must agree with ``march_bisect`` (the same march, a different refiner) to xtol with the same
statuses, be CONVERGED only where scipy's *returned* bracket is certified (not on scipy's flag),
and be declined cleanly by the backends that do not offer it."""

from __future__ import annotations

import types

import numpy as np
import pytest

from impls import METHODS, Status, registry
from impls.core import chandrupatla
from reference.cases import get_case

NUMPY = registry.resolve("numpy")


def run(method, scene, o, d, **kw):
    t_min, t_max = kw.pop("t_min", 0.0), kw.pop("t_max", 10.0)
    p = NUMPY.prepare(method, scene, o, d, t_min=t_min, t_max=t_max, **kw)
    return p.result(p.run())


@pytest.mark.parametrize("case_id", ["sphere.camera.64x64", "torus.camera.32x32", "torus.grazing.1e-3",
                                     "sphere.grazing.1e-3", "sphere.far.1e6", "csg.union.camera.32x32"])
def test_agrees_with_march_bisect_to_xtol(case_id):
    case = get_case(case_id)
    kw = dict(t_min=case.t_min, t_max=case.t_max, xtol=1e-12)
    a = run("march_bisect", case.scene, case.origins, case.directions, **kw)
    c = run("march_chandrupatla", case.scene, case.origins, case.directions, **kw)
    np.testing.assert_array_equal(c.status, a.status)  # the same march: the same brackets and outcomes
    conv = c.status == Status.CONVERGED
    assert conv.mean() > 0.2  # (grazing: rays whose chord is shorter than the step are missed by both)
    # both report a point of a certified bracket of the same root: within xtol of each other, or of
    # adjacent floats where xtol is below the float spacing (sphere.far.1e6: t ≈ 1e6, spacing 1.2e-10)
    slack = 1e-12 + 2 * np.spacing(np.abs(a.t[conv]))
    assert np.all(np.abs(c.t[conv] - a.t[conv]) <= 2 * slack), np.max(np.abs(c.t[conv] - a.t[conv]))
    # against the exact hit, where the case has one and the march found it
    exact = case.scene.first_hit(case.origins, case.directions, case.t_min)
    with np.errstate(invalid="ignore"):  # inf − inf on misses
        both = conv & np.isfinite(exact) & (np.abs(a.t - exact) <= 1e-9)
    assert np.all(np.abs(c.t[both] - exact[both]) <= 1e-9)
    assert np.all(np.isinf(c.t[c.status == Status.MISS]))
    # scipy refines in fewer evaluations than bisection (and counts every one it makes)
    assert c.evals[conv].mean() < a.evals[conv].mean()


@pytest.mark.parametrize("case_id", ["torus.camera.32x32", "torus.grazing.1e-6", "sphere.grazing.1e-9",
                                     "csg.union.camera.32x32"])
def test_hybrid_chandrupatla_agrees_with_hybrid_secant(case_id):
    """The certified march of hybrid_secant, refined by scipy: the same statuses, depths within xtol."""
    case = get_case(case_id)
    kw = dict(t_min=case.t_min, t_max=case.t_max, xtol=1e-12)
    a = run("hybrid_secant", case.scene, case.origins, case.directions, **kw)
    c = run("hybrid_chandrupatla", case.scene, case.origins, case.directions, **kw)
    np.testing.assert_array_equal(c.status, a.status)
    conv = c.status == Status.CONVERGED
    # (the grazing cases' hits are approached below the hybrids' passing slope, on forced steps that
    # stand uncertified: UNCERTIFIED on both, whose statuses still agree ray by ray)
    if "grazing" not in case_id:
        assert conv.mean() > 0.2
    # both brackets hold a sign change of φ as evaluated, ≤ xtol wide; where the ray grazes, φ's
    # rounding (≈ 8ε(|o| + t)) moves that sign change by up to its size over |φ'| = |⟨n, d⟩|
    cos = np.abs(np.einsum("ij,ij->i", case.exact_normals[conv], case.directions[conv]))
    slack = 2e-12 + 8 * np.finfo(float).eps * (np.linalg.norm(case.origins[conv], axis=1) + a.t[conv]) / cos
    assert np.all(np.abs(c.t[conv] - a.t[conv]) <= slack)


def _fake_find_root(bracket, f_bracket, x, f_x, status, nit=3, nfev=5):
    def find_root(f, init, *, args=(), tolerances=None, maxiter=None):
        n = np.shape(init[0])
        full = lambda v: np.broadcast_to(np.asarray(v, float), n).copy()  # noqa: E731
        return types.SimpleNamespace(bracket=(full(bracket[0]), full(bracket[1])),
                                     f_bracket=(full(f_bracket[0]), full(f_bracket[1])), x=full(x), f_x=full(f_x),
                                     status=np.full(n, status), nit=np.full(n, nit), nfev=np.full(n, nfev))
    return find_root


@pytest.mark.parametrize("bracket,f_bracket,x,f_x,code,want", [
    ((1.0, 1.0 + 1e-13), (-1e-13, 1e-13), 1.0, -1e-13, 0, Status.CONVERGED),  # ≤ xtol with a sign change
    ((1.0, np.nextafter(1.0, 2.0)), (-1e-16, 1e-16), 1.0, -1e-16, -2, Status.CONVERGED),  # adjacent floats
    ((1.0, 1.0 + 1e-6), (-1e-6, 1e-6), 1.0, -1e-6, 0, Status.MAX_ITER),  # scipy "converged", bracket too wide
    ((1.0, 1.0 + 1e-13), (1e-13, 2e-13), 1.0, 1e-13, 0, Status.MAX_ITER),  # narrow, but no sign change
    ((1.0, 1.5), (-0.5, 0.0), 1.5, 0.0, 0, Status.CONVERGED),  # φ = 0 exactly at x
    ((1.0, 1.5), (-0.5, 0.5), 1.2, 0.1, -2, Status.MAX_ITER),  # budget spent
    ((np.nan, np.nan), (np.nan, np.nan), np.nan, np.nan, -3, Status.NON_FINITE),
])
def test_converged_only_on_a_certified_returned_bracket(monkeypatch, bracket, f_bracket, x, f_x, code, want):
    import scipy.optimize.elementwise as el

    monkeypatch.setattr(el, "find_root", _fake_find_root(bracket, f_bracket, x, f_x, code))
    a, b = np.array([0.5, 0.5]), np.array([2.0, 2.0])
    o, d = np.zeros((2, 3)), np.tile([1.0, 0.0, 0.0], (2, 1))
    ev = lambda o, d, t, deriv: (t - 1.0, None, 1)  # noqa: E731
    t, status, nit, evals, _ = chandrupatla.refine(a, b, a - 1.0, b - 1.0, o, d, ev, xtol=1e-12, budget=np.array([100, 100]))
    assert np.all(status == want)
    assert np.all(np.isnan(t)) if want == Status.NON_FINITE else np.all(np.isfinite(t))
    assert np.all(nit == 3) and np.all(evals == 5)  # the fake never asks for φ: nothing served from the march


def test_real_scipy_counts_evaluations_and_respects_the_budget():
    """φ(t) = t − 1 on [0.5, 2] per ray: scipy's bracket ends come from the march (not re-evaluated:
    evals = nfev − 2, equal to the points φ was called on); one iteration of budget is MAX_ITER."""
    a, b = np.array([0.5, 0.25]), np.array([2.0, 1.5])
    o, d = np.zeros((2, 3)), np.tile([1.0, 0.0, 0.0], (2, 1))
    seen = []

    def ev(o, d, t, deriv):
        seen.append(t.size)
        return np.cbrt(t - 1.0), None, 1

    t, status, nit, evals, _ = chandrupatla.refine(a, b, np.cbrt(a - 1), np.cbrt(b - 1), o, d, ev, xtol=1e-12,
                                                budget=np.array([200, 200]))
    assert np.all(status == Status.CONVERGED) and np.all(np.abs(t - 1.0) <= 1e-12)
    assert int(evals.sum()) == sum(seen) and np.all(nit >= 1)
    t, status, nit, evals, _ = chandrupatla.refine(a, b, np.cbrt(a - 1), np.cbrt(b - 1), o, d, ev, xtol=1e-12,
                                                budget=np.array([1, 200]))
    assert status[0] == Status.MAX_ITER and status[1] == Status.CONVERGED


@pytest.mark.filterwarnings("ignore:invalid value:RuntimeWarning")
def test_statuses_on_miss_bad_input_budget_and_nan_field():
    from reference import Sphere
    from reference.numerical import CallableField

    sphere = Sphere()
    o = np.array([[0.0, 0.0, 3.0], [0.0, 5.0, 3.0], [np.nan, 0.0, 3.0], [0.0, 0.0, 3.0]])
    d = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0], [0.0, 0.0, -1.0], [0.0, 0.0, 0.0]])
    r = run("march_chandrupatla", sphere, o, d, xtol=1e-12)
    assert r.status.tolist() == [Status.CONVERGED, Status.MISS, Status.BAD_INPUT, Status.BAD_INPUT]
    assert abs(r.t[0] - 2.0) <= 1e-12 and np.isinf(r.t[1]) and np.all(np.isnan(r.t[2:]))
    # a march that crosses, then a budget too small for the refinement
    o2 = np.array([[0.0, 0.5, 3.0]])  # φ(t) = √(0.25 + (3 − t)²) − 1: not linear in t
    r = run("march_chandrupatla", sphere, o2, d[:1], xtol=1e-14, step=0.3, max_steps=2, bounds=0, t_min=1.9)
    assert r.status[0] == Status.MAX_ITER and r.iterations[0] >= 2 and r.evals[0] >= 3
    r = run("march_chandrupatla", sphere, o2, d[:1], xtol=1e-14, step=0.3, max_steps=20, bounds=0, t_min=1.9)
    assert r.status[0] == Status.CONVERGED and abs(r.t[0] - (3 - np.sqrt(0.75))) <= 1e-14
    # φ NaN everywhere: NON_FINITE at the start, as every marcher
    nan_field = CallableField(lambda x, xp: xp.sum(x, axis=-1) * np.nan, lipschitz=1.0)
    r = run("march_chandrupatla", nan_field, o[:1], d[:1])
    assert r.status[0] == Status.NON_FINITE and np.isnan(r.t[0])


def test_other_backends_decline_it_and_the_runner_skips_with_the_reason():
    from bench.run.configuration import Config, skip_reason

    assert METHODS["march_chandrupatla"].libs == ("numpy",)
    assert "march_chandrupatla" in NUMPY.methods()
    case = get_case("sphere.camera.64x64")
    for bid in ("torch:cpu", "jax:cpu"):
        b = registry.resolve(bid)
        if isinstance(b, registry.Unavailable):
            continue
        assert "march_chandrupatla" not in b.methods() and "march_bisect" in b.methods()
        with pytest.raises(NotImplementedError, match="march_chandrupatla"):
            b.prepare("march_chandrupatla", case.scene, case.origins[:2], case.directions[:2], t_max=10.0)
        cfg = Config(case=case, backend_id=bid, dtype="float64", method="march_chandrupatla", knobs={})
        assert "does not implement march_chandrupatla" in skip_reason(cfg, b)
