"""The grid-SDF reference (:mod:`reference.grid`): its exact hits checked against independent
methods, its convergence to an analytic surface, DDA ties, the three backends' φ and autodiff
gradients, its Lipschitz bound, and its input errors."""

from __future__ import annotations

import functools

import array_api_compat.torch as xp_torch
import jax
import jax.numpy as jnp
import mpmath
import numpy as np
import pytest
import torch

from reference import rays as _rays
from reference.grid import GridSDF, grid_cases, grid_from_field
from reference.numerical import first_hit_numeric
from reference.primitives import Sphere, Torus

jax.config.update("jax_enable_x64", True)
EPS = np.finfo(np.float64).eps


@functools.cache
def _cases():
    return {c.id: c for c in grid_cases()}


def _box_chord(g: GridSDF, o, d):
    with np.errstate(divide="ignore", invalid="ignore"):
        a, b = (g.lo - o) / d, (g.hi - o) / d
    t0 = np.nanmax(np.fmin(a, b), axis=1)
    t1 = np.nanmin(np.fmax(a, b), axis=1)
    return np.maximum(t0, 0.0), t1


def _dense_crossings(g: GridSDF, o, d, n=6001, first=True):
    """Independent float64 reference: φ (GridSDF.value) sampled at n points on the box chord,
    each sign change of "φ > 0" bisected to adjacent floats (the first one, or all)."""
    t0, t1 = _box_chord(g, o, d)
    out = []
    for i in range(o.shape[0]):
        if not t0[i] <= t1[i]:
            out.append(np.zeros(0))
            continue
        ts = np.linspace(t0[i], t1[i], n)
        s = g.value(o[i] + ts[:, None] * d[i]) > 0
        found = []
        for j in np.flatnonzero(s[1:] != s[:-1]):
            lo, hi, slo = ts[j], ts[j + 1], s[j]
            while True:
                mid = lo + (hi - lo) / 2
                if not lo < mid < hi:
                    break
                if (g.value((o[i] + mid * d[i])[None])[0] > 0) == slo:
                    lo = mid
                else:
                    hi = mid
            found.append(hi)
            if first:
                break
        out.append(np.array(found))
    return out


def _first(cross):
    return np.array([c[0] if c.size else np.inf for c in cross])


def _mp_phi(g: GridSDF, x):
    """φ at an mpmath point x (3 mpf): the module's formula in multiprecision."""
    n = g.shape
    gg = [(x[k] - mpmath.mpf(g.lo[k])) / mpmath.mpf(g.spacing[k]) for k in range(3)]
    p = [min(max(gg[k], mpmath.mpf(0)), mpmath.mpf(n[k] - 1)) for k in range(3)]
    c = [min(int(mpmath.floor(p[k])), n[k] - 2) for k in range(3)]
    u = [p[k] - c[k] for k in range(3)]
    tot = mpmath.mpf(0)
    for a in (0, 1):
        for b in (0, 1):
            for e in (0, 1):
                w = (u[0] if a else 1 - u[0]) * (u[1] if b else 1 - u[1]) * (u[2] if e else 1 - u[2])
                tot += w * mpmath.mpf(float(g.values[c[0] + a, c[1] + b, c[2] + e]))
    dist = mpmath.sqrt(sum(((gg[k] - p[k]) * mpmath.mpf(g.spacing[k])) ** 2 for k in range(3)))
    return tot + dist


def _mp_first_hit(g: GridSDF, o, d, t0, t1, n=600):
    """Dense sampling + bisection entirely in mpmath (50 digits) on the real-number φ."""
    with mpmath.workdps(50):
        om, dm = [mpmath.mpf(float(v)) for v in o], [mpmath.mpf(float(v)) for v in d]
        f = lambda t: _mp_phi(g, [om[k] + t * dm[k] for k in range(3)])
        a = mpmath.mpf(float(t0))
        step = (mpmath.mpf(float(t1)) - a) / n
        fa = f(a)
        for j in range(1, n + 1):
            b = a + step
            fb = f(b)
            if (fa > 0) != (fb > 0):
                for _ in range(170):
                    m = (a + b) / 2
                    if (f(m) > 0) == (fa > 0):
                        a = m
                    else:
                        b = m
                return float(b)
            a, fa = b, fb
    return np.inf


# -- (a) exact hits against independent methods --------------------------------------------------
@pytest.mark.parametrize("cid", ["grid.torus32.camera.32x32", "grid.torus64.camera.32x32", "grid.torus64.grazing.1e-6"])
def test_case_hits_match_dense_sampling_and_certified_reference(cid):
    """The cases' exact first hits equal (≤ 1e-12 relative) dense float64 sampling + bisection of
    φ (every hit it sees; on camera rays the same hit/miss set), and the Lipschitz-certified
    numerical reference, which cannot step over a hit (the same hit/miss set on every case)."""
    case = _cases()[cid]
    t = case.exact_t
    assert np.isfinite(t).sum() >= 64, "a case with few hits checks little"
    dense = _first(_dense_crossings(case.scene, case.origins, case.directions))
    dense = np.where(dense <= case.t_max, dense, np.inf)
    seen = np.isfinite(dense)
    assert np.all(np.isfinite(t[seen]))
    # grazing hits span less than the sample spacing (≈ 1e-3 here), so sampling may step over them
    assert "grazing" in case.tags or np.array_equal(np.isfinite(t), seen)
    assert np.max(np.abs(t[seen] - dense[seen]) / t[seen]) <= 1e-12
    m = np.isfinite(t)
    num, err = first_hit_numeric(case.scene, case.origins, case.directions, case.t_min, case.t_max)
    assert np.array_equal(np.isfinite(t), np.isfinite(num))
    assert np.max(np.abs(t[m] - num[m]) / t[m]) <= 1e-12


def test_hits_match_mpmath():
    """A sample of camera rays (hits and misses): the float64 reference against dense sampling
    and bisection of the real-number φ in 50-digit mpmath, ≤ 1e-12 relative."""
    case = _cases()["grid.torus64.camera.32x32"]
    g = case.scene
    rng = np.random.default_rng(3)
    hits = np.flatnonzero(case.hit_mask)
    sel = np.concatenate([rng.choice(hits, 10, replace=False), rng.choice(np.flatnonzero(~case.hit_mask), 2, replace=False)])
    o, d = case.origins[sel], case.directions[sel]
    t0, t1 = _box_chord(g, o, d)
    ref = g.first_hit(o, d)
    for i in range(len(sel)):
        mp = _mp_first_hit(g, o[i], d[i], t0[i], t1[i]) if t0[i] <= t1[i] else np.inf
        if np.isinf(mp):
            assert np.isinf(ref[i])
        else:
            assert abs(ref[i] - mp) <= 1e-12 * mp, (i, ref[i], mp)


def test_all_crossings_match_dense_sampling():
    """ray_intervals: every crossing of the 32³ torus grid, on oblique rays through the tube and
    the hole (4 crossings) or the tube only (2), against dense sampling; they alternate enter/exit."""
    g = _cases()["grid.torus32.camera.32x32"].scene
    rng = np.random.default_rng(4)
    n = 128
    o = np.stack([np.full(n, -3.0), rng.uniform(-1.3, 1.3, n), rng.uniform(-0.2, 0.2, n)], axis=1)
    d = _rays.normalize(np.stack([np.ones(n), rng.uniform(-0.05, 0.05, n), rng.uniform(-0.03, 0.03, n)], axis=1))
    iv = g.ray_intervals(o, d)
    dense = _dense_crossings(g, o, d, first=False)
    counts = [len(a) for a in iv]
    assert 4 in counts and 2 in counts
    for a, b, oi, di in zip(iv, dense, o, d):
        assert a.shape == b.shape and len(a) % 2 == 0
        if a.size:
            assert np.max(np.abs(a - b) / b) <= 1e-12
            mids = (a[:-1] + a[1:]) / 2
            inside = g.value(oi + mids[:, None] * di) <= 0
            assert np.array_equal(inside, np.arange(mids.size) % 2 == 0), "crossings alternate enter/exit"


def test_case_hits_lie_on_the_surface():
    """Backward error of every grid case's hit: |φ(x*)|/|∇φ(x*)| ≤ 16 ε (|o| + t + 1), as the
    catalog's closed-form cases are held to; and the grazing family brackets the tangency (the
    rays offset outward miss, inward hit)."""
    for case in _cases().values():
        if "large" in case.tags:  # the 32×32 view at 256² and 1024²: the same function, minutes of answers
            continue
        m = case.hit_mask
        x = case.exact_points[m]
        phi, grad, _ = case.scene.jet(x)
        bound = 16 * EPS * (np.linalg.norm(case.origins[m], axis=1) + case.exact_t[m] + 1.0)
        assert np.all(np.abs(phi) / np.linalg.norm(grad, axis=1) <= bound), case.id
    graz = _cases()["grid.torus64.grazing.1e-6"]
    out = np.arange(graz.n_rays) % 2 == 0
    assert not graz.hit_mask[out].any() and graz.hit_mask[~out].all()


@pytest.mark.slow  # 51 exact grid marches of 256 rays
def test_stored_grazing_offsets_are_the_bisections():
    """The grazing case's stored tangent offsets (reference/data, read instead of recomputed by
    every process that builds the case, where their key is this platform's) are bit for bit what
    the bisection gives now, and each splits the rays it offsets: inward hits, outward misses."""
    from reference import grid

    g, dirs, lateral = grid._grazing_family()
    with np.load(grid.GRAZING_OFFSETS) as f:
        assert str(f["key"]) == grid._grazing_key(g, dirs, lateral), ("stored for other rays or another grid: "
                                                                    "reference.grid.write_grazing_offsets()")
        stored = np.array(f["s_star"])
    np.testing.assert_array_equal(stored, grid._grazing_offsets(stored=False))
    np.testing.assert_array_equal(grid._grazing_offsets(), stored)
    for f, hits in ((1 - 1e-9, True), (1 + 1e-9, False)):
        o = (stored * f)[:, None] * lateral - 3.0 * dirs
        assert np.array_equal(np.isfinite(g.first_hit(o, dirs)), np.full(len(stored), hits))


# -- (b) convergence to an analytic surface --------------------------------------------------------
def test_sphere_grid_converges_at_second_order():
    """A sphere SDF (r = 0.8) sampled on [−1, 1]³ at 16…128 vertices per axis: the grid's first
    hits tend to the sphere's closed-form hits at O(h²) (rays meeting the sphere at incidence
    cos > 0.3, so depth error ≈ surface error / cos)."""
    sph = Sphere(radius=0.8)
    o, d = _rays.pinhole(eye=(0.3, 0.2, 3.0), look_at=(0.0, 0.0, 0.0), fov_deg=30.0, width=24, height=24)
    t_true = sph.first_hit(o, d)
    m = np.isfinite(t_true)
    x = o[m] + t_true[m, None] * d[m]
    m[m] = -np.einsum("ij,ij->i", x / 0.8, d[m]) > 0.3
    errs, hs = [], []
    for n in (16, 32, 64, 128):
        g = grid_from_field(sph, (-1.0,) * 3, (1.0,) * 3, n)
        t = g.first_hit(o[m], d[m])
        assert np.all(np.isfinite(t))
        errs.append(np.max(np.abs(t - t_true[m])))
        hs.append(2.0 / (n - 1))
    slope = np.polyfit(np.log(hs), np.log(errs), 1)[0]
    ratios = np.array(errs[:-1]) / np.array(errs[1:])
    assert 1.8 <= slope <= 2.3, (slope, errs)
    assert np.all(ratios > 3.0), ratios


# -- (c) DDA ties: rays in grid planes, along grid edges, through grid vertices ------------------------
@functools.cache
def _dyadic_sphere_grid():
    """A sphere (r = 0.6) on a grid with spacing 1/8 and corner −1: every vertex coordinate is an
    exact binary fraction, so rays can lie exactly in grid planes and pass exactly through vertices."""
    return grid_from_field(Sphere(radius=0.6, center=(0.05, -0.03, 0.02)), (-1.0,) * 3, (1.0,) * 3, 17)


def _tie_rays():
    o, d = [], []
    for y in (0.25, 0.0, -0.125):  # in the plane y = const, oblique in x–z: crosses x and z planes
        o.append((-2.0, y, -0.7))
        d.append((1.0, 0.0, 0.375))
    for y, z in ((0.25, -0.5), (0.0, 0.125), (-0.375, 0.0)):  # along a grid edge (x axis)
        o.append((-2.0, y, z))
        d.append((1.0, 0.0, 0.0))
    for v in ((0.25, 0.0, 0.5), (0.0, 0.0, 0.0), (-0.125, 0.25, 0.125)):  # through vertices along (1, 1, 1)
        o.append(tuple(np.array(v) - 2.0))
        d.append((1.0, 1.0, 1.0))
    for v in ((0.25, 0.0, 0.5), (0.0, -0.25, 0.0)):  # diagonal in a plane: double ties at every edge
        o.append((v[0] - 2.0, v[1] - 2.0, v[2]))
        d.append((1.0, 1.0, 0.0))
    for v in ((0.5, 0.125, 0.0),):  # reversed directions take the ⌈g⌉ − 1 index rule
        o.append((v[0] + 2.0, v[1] + 2.0, v[2] + 2.0))
        d.append((-1.0, -1.0, -1.0))
    return np.array(o, np.float64), np.array(d, np.float64)


def test_dda_ties_match_dense_sampling_and_nearby_rays():
    """Rays exactly in a grid plane, along a grid edge and through grid vertices (where the DDA
    steps two or three axes at once): every crossing equals dense sampling (≤ 1e-12 relative),
    and the first hit is continuous — rays shifted by 1e-12 off the ties hit within 1e-9."""
    g = _dyadic_sphere_grid()
    o, d = _tie_rays()
    iv = g.ray_intervals(o, d)
    dense = _dense_crossings(g, o, d, first=False)
    for a, b in zip(iv, dense):
        assert a.size == 2 and b.size == 2, "every tie ray is aimed through the sphere"
        assert np.max(np.abs(a - b) / b) <= 1e-12
    t = g.first_hit(o, d)
    rng = np.random.default_rng(5)
    t_shift = g.first_hit(o + 1e-12 * rng.uniform(-1, 1, o.shape), d)
    assert np.max(np.abs(t_shift - t)) <= 1e-9


# -- (d) backends: φ and autodiff gradients ---------------------------------------------------------------
def _sample_points(g, n=300, seed=7):
    """Points inside the box and up to 0.5 outside it (none on a cell face)."""
    rng = np.random.default_rng(seed)
    return rng.uniform(g.lo - 0.5, g.hi + 0.5, size=(n, 3))


@pytest.mark.parametrize("lib", ["torch", "jax"])
def test_backends_phi_and_gradients_match_numpy_and_analytic(lib):
    """φ of torch and jax equals numpy's, and their autodiff ∇φ equals the analytic gradient of
    :meth:`GridSDF.jet` (trilinear inside, distance outside), ≤ 1e-13."""
    g = grid_from_field(Torus(1.0, 0.25), (-1.4, -1.3, -0.6), (1.4, 1.5, 0.6), (24, 26, 12))
    x = _sample_points(g)
    phi_np = g.value(x)
    phi_jet, grad_jet, _ = g.jet(x)
    assert np.max(np.abs(phi_np - phi_jet)) <= 1e-13
    if lib == "torch":
        xt = torch.tensor(x, requires_grad=True)
        phi = g.value(xt, xp_torch)
        (gr,) = torch.autograd.grad(phi.sum(), xt)
        phi, gr = phi.detach().numpy(), gr.numpy()
    else:
        phi = np.asarray(g.value(jnp.asarray(x), jnp))
        gr = np.asarray(jax.grad(lambda y: jnp.sum(g.value(y, jnp)))(jnp.asarray(x)))
        jitted = np.asarray(jax.jit(lambda y: g.value(y, jnp))(jnp.asarray(x)))
        assert np.max(np.abs(jitted - phi_np)) <= 1e-13
    assert np.max(np.abs(phi - phi_np)) <= 1e-13
    assert np.max(np.abs(gr - grad_jet)) <= 1e-13
    fd = np.stack([(g.value(x + 1e-6 * e) - g.value(x - 1e-6 * e)) / 2e-6 for e in np.eye(3)], axis=1)
    assert np.max(np.abs(fd - grad_jet)) <= 1e-6  # the analytic gradient itself (FD error ~ h² φ''' + ε/h)


@pytest.mark.parametrize("lib", ["torch", "jax"])
def test_differentiable_values_gradients(lib):
    """With ``differentiable=True`` the samples are θ: autodiff ∂φ/∂θ of torch and jax equals the
    trilinear weights of :meth:`GridSDF.jet`, and with_params round-trips."""
    rng = np.random.default_rng(9)
    g = GridSDF(rng.normal(size=(4, 5, 3)), lo=(-1.0, -0.5, 0.0), spacing=(0.5, 0.3, 0.7), differentiable=True)
    theta = g.param_vector()
    assert theta.size == 60 and np.array_equal(theta, g.values.ravel())
    x = _sample_points(g, 40, seed=10)
    _, _, dth = g.jet(x)
    assert np.allclose(dth.sum(axis=1), 1.0, rtol=0, atol=1e-14)  # trilinear weights (at the clamped point outside)
    if lib == "torch":
        th = torch.tensor(theta, requires_grad=True)
        jac = torch.autograd.functional.jacobian(lambda p: g.value(torch.tensor(x), xp_torch, p), th).numpy()
    else:
        jac = np.asarray(jax.jacfwd(lambda p: g.value(jnp.asarray(x), jnp, p))(jnp.asarray(theta)))
    assert np.max(np.abs(jac - dth)) <= 1e-13
    g2 = g.with_params(theta + 1.0)
    assert np.allclose(g2.value(x), g.value(x) + 1.0, atol=1e-13)  # the weights sum to 1


# -- Lipschitz bound ----------------------------------------------------------------------------------------------
def test_lipschitz_bound_holds_on_random_segments():
    """|φ(x) − φ(y)| ≤ L |x − y| on random short and long segments inside, across and outside the
    box, for a torus grid and a grid of random samples (large slopes, boundary values of both signs)."""
    rng = np.random.default_rng(11)
    grids = [_cases()["grid.torus32.camera.32x32"].scene,
             GridSDF(rng.normal(size=(6, 7, 5)), lo=(0.0, 0.0, 0.0), spacing=(0.2, 0.5, 0.3))]
    for g in grids:
        L = g.info.lipschitz
        worst = 0.0
        for scale in (1e-4, 1e-2, 0.3, 3.0):
            x = _sample_points(g, 20000, seed=int(scale * 1e4))
            y = x + scale * _rays.normalize(rng.normal(size=x.shape)) * rng.uniform(0, 1, (x.shape[0], 1))
            ratio = np.abs(g.value(x) - g.value(y)) / (L * np.linalg.norm(x - y, axis=1))
            worst = max(worst, ratio.max())
        assert worst <= 1 + 1e-9, worst
        assert worst >= 0.5, "the bound is far above every slope seen"


def test_lipschitz_bound_of_a_linear_field_is_tight():
    """For samples of φ = a·x (reproduced exactly by trilinear interpolation) the derived bound is
    max(|a|, √(1 + maxₖ |a − aₖeₖ|²)) — off the face normal to eₖ, ∇φ = a − aₖeₖ ± eₖ — and it is
    attained: |∇φ| (finite differences) reaches it inside or just off a face."""
    for a in (np.array([2.0, 0.3, -0.4]), np.array([0.1, 0.3, -0.4]), np.array([3.0, 0.0, 0.0])):
        g = GridSDF(np.fromfunction(lambda i, j, k: (np.stack([i, j, k], -1) * 0.1) @ a, (5, 6, 7)), spacing=0.1)
        expect = max(np.linalg.norm(a), np.sqrt(1 + max(a @ a - a[k] ** 2 for k in range(3))))
        assert g.info.lipschitz == pytest.approx(expect, rel=1e-14)
        x = np.array([g.hi / 2, [0.2, -0.5, 0.3], [-0.5, 0.25, 0.3], [0.2, 0.25, -0.5]])  # inside; off the y, x, z faces
        fd = np.stack([(g.value(x + 1e-7 * e) - g.value(x - 1e-7 * e)) / 2e-7 for e in np.eye(3)], axis=1)
        assert np.max(np.linalg.norm(fd, axis=1)) == pytest.approx(expect, rel=1e-7)


# -- info, identity, open grids ----------------------------------------------------------------------------------
def test_info_spec_and_bounds():
    g = _cases()["grid.torus32.camera.32x32"].scene
    info = g.info
    assert not info.exact_sdf and info.exact_hits and info.exact_normals and not info.exact_hit_param_grad
    assert g.param_vector().size == 0
    same = grid_from_field(Torus(1.0, 0.25), (-1.4,) * 3, (1.4,) * 3, 32)
    assert same.content_hash() == g.content_hash()
    other = GridSDF(np.array(g.values) + 1e-15 * (np.arange(g.values.size).reshape(g.shape) == 5), g.lo, g.spacing)
    assert other.content_hash() != g.content_hash()
    case = _cases()["grid.torus32.camera.32x32"]
    lo, hi = g.ray_bounds(np, case.origins, case.directions)
    m = case.hit_mask
    assert np.all((lo[m] <= case.exact_t[m]) & (case.exact_t[m] <= hi[m]))


def test_open_grid_has_no_exact_hits_and_bounds_its_zero_set():
    """A grid whose boundary samples are ≤ 0 (the surface may leave the box) declares exact_hits
    False, first_hit says why, and its bounding ball still contains every point with φ ≤ 0."""
    g = GridSDF(np.full((3, 3, 3), -0.5), lo=(0.0, 0.0, 0.0), spacing=1.0)
    assert not g.info.exact_hits
    with pytest.raises(ValueError, match="boundary sample"):
        g.first_hit(np.zeros((1, 3)), np.array([[1.0, 0.0, 0.0]]))
    c, r = g.bounding_sphere()
    rng = np.random.default_rng(2)
    x = rng.uniform(-3, 5, size=(20000, 3))
    inside = g.value(x) <= 0
    assert inside.any() and np.all(np.linalg.norm(x[inside] - c, axis=1) <= r)


# -- (e) bad inputs --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kwargs, match", [
    (dict(values=np.full((3, 3, 3), np.nan)), "values must be finite"),
    (dict(values=np.ones((3, 3))), r"shape \(nx, ny, nz\)"),
    (dict(values=np.ones((3, 1, 3))), "every n ≥ 2"),
    (dict(values=np.ones((3, 3, 3)), spacing=0.0), "spacing must be a finite number > 0"),
    (dict(values=np.ones((3, 3, 3)), spacing=(1.0, -1.0, 1.0)), "spacing"),
    (dict(values=np.ones((3, 3, 3)), spacing=(1.0, 1.0)), "spacing"),
    (dict(values=np.ones((3, 3, 3)), lo=(0.0, 0.0)), "lo"),
    (dict(values=np.ones((3, 3, 3)), lo=(0.0, np.inf, 0.0)), "lo"),
    (dict(values="abc"), "values"),
])
def test_bad_inputs_raise_clear_errors(kwargs, match):
    with pytest.raises(ValueError, match=match):
        GridSDF(**kwargs)


def test_grid_from_field_bad_inputs():
    with pytest.raises(ValueError, match="hi must exceed lo"):
        grid_from_field(Sphere(), (0.0,) * 3, (0.0, 1.0, 1.0), 8)
    with pytest.raises(ValueError, match="n must be a whole number"):
        grid_from_field(Sphere(), (-1.0,) * 3, (1.0,) * 3, 1)
    with pytest.raises(ValueError, match="n must be a whole number"):
        grid_from_field(Sphere(), (-1.0,) * 3, (1.0,) * 3, 8.5)
