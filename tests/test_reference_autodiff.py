"""The reference derivatives of a user's smooth field (jax autodiff, reference/autodiff.py): checked
against closed forms, refused where the user's code cannot give them, and used by the gradient
rows of a user's case."""

from __future__ import annotations

import os
import textwrap

import numpy as np
import pandas as pd
import pytest

from reference.implicits import Ellipsoid
from reference.numerical import CallableField
from reference.primitives import Sphere, Torus
from reference.transform import Transform
from tests.conftest import bench_cli

pytest.importorskip("jax")


def _sphere(x, xp):
    return xp.sqrt(xp.sum(x * x, axis=-1)) - 0.7


def _ellipsoid(x, xp):
    return (x[..., 0] / 1.0) ** 2 + (x[..., 1] / 0.75) ** 2 + (x[..., 2] / 0.5) ** 2 - 1.0


def _torus(x, xp):
    q = xp.sqrt(x[..., 0] ** 2 + x[..., 1] ** 2) - 1.0
    return xp.sqrt(q * q + x[..., 2] ** 2) - 0.25


def _surface_points(field, n: int, seed: int) -> np.ndarray:
    """First hits of random rays from a sphere of radius 3 aimed near the origin (exact hits)."""
    rng = np.random.default_rng(seed)
    o = rng.normal(size=(n, 3))
    o = 3.0 * o / np.linalg.norm(o, axis=1, keepdims=True)
    d = rng.uniform(-0.3, 0.3, (n, 3)) - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t = field.first_hit(o, d, 0.0)
    hit = np.isfinite(t)
    return (o + t[:, None] * d)[hit]


@pytest.mark.parametrize("fn, exact", [(_sphere, Sphere(radius=0.7)), (_ellipsoid, Ellipsoid()),
                                       (_torus, Torus(major=1.0, minor=0.25))], ids=["sphere", "ellipsoid", "torus"])
def test_autodiff_normals_and_curvatures_match_the_closed_forms(fn, exact):
    """On a few thousand surface points of each closed form: normals within 1e-14 rad, κ1 and κ2
    within 1e-12 relative to the largest |κ| (the module's stated accuracy)."""
    x = _surface_points(exact, 4000, 1)
    assert len(x) > 1000
    user = CallableField(fn, name=f"user {fn.__name__}", smooth=True)
    n_user, n_ref = user.normal_exact(x), exact.normal_exact(x)
    angle = np.arctan2(np.linalg.norm(np.cross(n_user, n_ref), axis=1), np.einsum("ij,ij->i", n_user, n_ref))
    assert np.max(angle) < 1e-14, np.max(angle)
    (k1, k2), (e1, e2) = user.curvatures_exact(x), exact.curvatures_exact(x)
    scale = np.max(np.abs([e1, e2]))
    assert np.max(np.abs(k1 - e1)) < 1e-12 * scale and np.max(np.abs(k2 - e2)) < 1e-12 * scale


def test_a_moved_field_takes_the_derivatives_of_its_own_code():
    """A field written with a rotation and a shift inside fn: the Hessian carries them (another
    field than the axis-aligned ellipsoid, compared with the library's Transform of it)."""
    c, s = np.cos(0.4), np.sin(0.4)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    shift = np.array([0.1, -0.2, 0.05])

    def moved(x, xp):
        local = (x - xp.asarray(shift)) @ xp.asarray(rot)  # local = Rᵀ(x − shift), rows
        return _ellipsoid(local, xp)

    exact = Transform(Ellipsoid(), rotation=tuple(map(tuple, rot)), translation=tuple(shift))
    x = _surface_points(exact, 2000, 2)
    user = CallableField(moved, name="moved ellipsoid", smooth=True)
    assert np.max(np.abs(exact.value(x) - user.value(x))) < 1e-12  # the same field
    n_user, n_ref = user.normal_exact(x), exact.normal_exact(x)
    assert np.max(np.linalg.norm(n_user - n_ref, axis=1)) < 1e-13
    (k1, k2), (e1, e2) = user.curvatures_exact(x), exact.curvatures_exact(x)
    assert np.max(np.abs(k1 - e1)) < 1e-11 and np.max(np.abs(k2 - e2)) < 1e-11


def test_the_field_states_what_it_declares():
    plain = CallableField(_sphere, lipschitz=1.0, name="plain")
    smooth = CallableField(_sphere, lipschitz=1.0, name="plain", smooth=True)
    assert not plain.info.smooth and not plain.info.exact_normals and not plain.info.exact_curvature
    assert smooth.info.smooth and smooth.info.exact_normals and smooth.info.exact_curvature
    assert not smooth.info.exact_hit_param_grad  # no θ: dt/dθ has nothing to differentiate
    # a field built without the flag keeps its content hash (its kept references and baselines)
    assert "smooth" not in plain.spec()["static"] and smooth.spec()["static"]["smooth"] is True
    with pytest.raises(NotImplementedError, match="smooth=True"):
        plain.normal_exact(np.array([[0.7, 0.0, 0.0]]))
    with pytest.raises(ValueError, match="smooth must be True or False"):
        CallableField(_sphere, smooth="yes")


def _torus_theta(x, xp, theta):  # the torus with θ = (R, r), as the library's Torus orders it
    q = xp.sqrt(x[..., 0] ** 2 + x[..., 1] ** 2) - theta[0]
    return xp.sqrt(q * q + x[..., 2] ** 2) - theta[1]


def test_a_parametrised_field_differentiates_its_hits_through_theta():
    """``params`` = θ: dt/dθ = −(∂φ/∂θ)/⟨∇φ, d⟩ by autodiff against the torus's closed form
    (within 1e-12 of the largest |dt/dθ|), θ in ``param_vector`` order, ``with_params`` a field
    of another θ (the finite-difference methods' way), and torch's autograd reaching θ."""
    user = CallableField(_torus_theta, lipschitz=1.0, name="torus(θ)", smooth=True, params=(1.0, 0.25))
    exact = Torus(major=1.0, minor=0.25)
    assert user.info.exact_hit_param_grad and np.array_equal(user.param_vector(), exact.param_vector())
    assert user.param_names() == ["0.callable.params[0]", "0.callable.params[1]"]
    rng = np.random.default_rng(3)
    o = rng.normal(size=(3000, 3))
    o = 4.0 * o / np.linalg.norm(o, axis=1, keepdims=True)
    d = rng.uniform(-0.5, 0.5, o.shape) - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t = exact.first_hit(o, d, 0.0)
    assert np.isfinite(t).sum() > 1000
    got, want = user.hit_param_grad(o, d, t), exact.hit_param_grad(o, d, t)
    assert np.array_equal(np.isnan(got), np.isnan(want))
    assert np.nanmax(np.abs(got - want)) < 1e-12 * np.nanmax(np.abs(want))
    other = user.with_params(np.array([1.0, 0.3]))
    assert type(other) is CallableField and other.params.tolist() == [1.0, 0.3] and user.params.tolist() == [1.0, 0.25]
    x = np.array([[1.3, 0.0, 0.0]])
    assert other.value(x)[0] == pytest.approx(0.0) and user.value(x)[0] == pytest.approx(0.05)
    assert other.spec() != user.spec()
    torch = pytest.importorskip("torch")
    theta = torch.tensor([1.0, 0.25], dtype=torch.float64, requires_grad=True)
    user.value(torch.tensor(x), torch, theta).sum().backward()
    assert theta.grad.tolist() == pytest.approx([-1.0, -1.0])


@pytest.mark.parametrize("params", [[], [[1.0]], ["a"], [np.inf], 3.0])
def test_bad_params_are_refused_naming_the_argument(params):
    with pytest.raises(ValueError, match="params must be a 1-D sequence of finite numbers"):
        CallableField(_torus_theta, params=params)


def test_a_field_without_theta_says_how_to_give_it_one():
    from bench.run.metrics import family_skip_reason
    from impls.methods import METHODS
    from reference import Case, rays

    o, d = rays.pinhole(eye=(0, 0, 3), look_at=(0, 0, 0), fov_deg=30, width=4, height=4)
    case = Case(id="user.plain.camera", scene=CallableField(_sphere, lipschitz=1.0, name="plain", smooth=True),
                origins=o, directions=d, t_min=0.0, t_max=6.0)
    assert "params=θ" in family_skip_reason(METHODS["dt_implicit"], case)
    assert family_skip_reason(METHODS["normal"], case) is None


def _numpy_only(x, xp):  # ignores xp: under jax its values are numpy's, its derivatives none
    return np.sqrt(np.sum(np.asarray(x) ** 2, axis=-1)) - 0.7


def _branches(x, xp):  # another function under jax than under numpy
    r = xp.sqrt(xp.sum(x * x, axis=-1))
    return r - (0.7 if xp is np else 0.6)


def _kinked(x, xp):  # |x₀| + x₁ − 0.5, declared C²: its derivative is not finite on its surface at x₀ = 0
    return xp.sqrt(x[..., 0] ** 2) + x[..., 1] - 0.5


@pytest.mark.parametrize("fn, match", [(_numpy_only, "jax's autodiff"), (_branches, "other values under jax"),
                                       (_kinked, "not finite")])
def test_a_field_whose_code_cannot_give_its_derivatives_is_refused_with_the_reason(fn, match):
    field = CallableField(fn, name="user field", smooth=True)
    x = np.array([[0.7, 0.0, 0.0], [0.0, 0.5, 0.0]]) if fn is _kinked else np.array([[0.7, 0.0, 0.0]])
    with pytest.raises(NotImplementedError, match=match):
        field.normal_exact(x)


def test_a_singular_point_off_the_surface_is_left_nan_as_the_closed_forms_leave_it():
    """|x| − 0.7 at its centre (which the rendering reference's samples reach on a ray through it):
    no error, NaN there as the closed-form sphere's jet gives, finite elsewhere."""
    field = CallableField(_sphere, lipschitz=1.0, name="sphere", smooth=True)
    _, g, _ = field.jet(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.7]]))
    with np.errstate(invalid="ignore"):  # (the closed form divides 0 by 0 there)
        _, g_exact, _ = Sphere(radius=0.7).jet(np.array([[0.0, 0.0, 0.0]]))
    assert np.isnan(g[0]).all() and np.isnan(g_exact[0]).all()
    assert g[1].tolist() == [0.0, 0.0, 1.0]


SMOOTH_USER_MODULE = textwrap.dedent("""
    from reference import Case, CallableField, rays

    def bumpy(x, xp, theta):
        r = xp.sqrt(xp.sum(x * x, axis=-1))
        bump = xp.sin(10 * x[..., 0] + 0.3) * xp.sin(10 * x[..., 1] + 1.1) * xp.sin(10 * x[..., 2])
        return r - theta[0] + theta[1] * bump

    o, d = rays.pinhole(eye=(0.4, 0.5, 2.5), look_at=(0, 0, 0), up=(0, 1, 0), fov_deg=40, width=16, height=16)
    field = CallableField(bumpy, lipschitz=1.0 + 0.5 * 3 ** 0.5, name="isobench_smooth_user.bumpy", smooth=True,
                          params=(0.8, 0.05))
    CASES = [Case(id="user.bumpy.camera", scene=field, origins=o, directions=d, t_min=0.0, t_max=6.0)]
""")


@pytest.mark.slow  # a bench run in a subprocess, compiling jax's kernels
def test_a_smooth_user_case_gets_gradient_rows_judged_against_autodiff(tmp_path):
    """A user's parametrised case in a run: normals, curvature and dt/dθ on numpy, torch and jax,
    each judged against the autodiff reference (numpy's central differences to ~1e-6, the
    autodiff backends to ~1e-12)."""
    (tmp_path / "isobench_smooth_user.py").write_text(SMOOTH_USER_MODULE)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")])}
    out = tmp_path / "run"
    p = bench_cli("run", "--cases", "isobench_smooth_user:CASES", "--case", "user.*", "--backend", "numpy,torch,jax",
                  "--method", "normal,curvature,dt_implicit", "--accuracy-only", "--no-claims", "--no-stability",
                  "--no-progress", "--out", out, env=env)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    df = pd.read_csv(out / "results.csv")
    got = df[df.outcome == "ok"].set_index(["backend", "method", "quantity"])["error_max"]
    ran = {b for b, _, _ in got.index}
    assert "numpy" in ran, df[["backend", "method", "outcome", "reason"]].to_string()
    assert got["numpy", "normal", "normal_angle"] < 1e-5
    for b in ran - {"numpy"}:
        assert got[b, "normal", "normal_angle"] < 1e-12, (b, got[b, "normal", "normal_angle"])
        curv = [q for (bb, m, q) in got.index if bb == b and m == "curvature"]
        assert curv and max(got[b, "curvature", q] for q in curv) < 1e-9, got[b].to_string()
    assert got["numpy", "dt_implicit", "dt_dtheta"] < 1e-5
    for b in ran - {"numpy"}:
        assert got[b, "dt_implicit", "dt_dtheta"] < 1e-10, (b, got[b, "dt_implicit", "dt_dtheta"])
