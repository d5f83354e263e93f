"""The surface and volume renderers against the continuous rendering integral (render_exact)
and the reference compositing."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from impls import METHODS, Status
from reference.rays import normalize
from reference.rendering import SineColor, render_exact
from tests.conformance.common import SPHERE, camera, hits, run

# -- renderers ----------------------------------------------------------------------------------


# A small case for the volume renderers: three rays from (0, 0, −3) hitting SPHERE at depths
# 2.26–2.64 at different incidence angles, sharpness s = 20 (transition width ~0.05), and a narrow
# window [t̂_min − 0.3, t̂_max + 0.3] around the surface that ends inside the sphere before φ has its
# minimum along the ray (NeuS's per-bin alpha is exact only where φ is monotone over the bin, and
# render_exact over long NeuS windows is slow).
VOL_O = np.tile([0.0, 0.0, -3.0], (3, 1))
VOL_D = normalize(np.array([[0.05, -0.04, 1.0], [0.2, -0.1, 1.0], [0.25, 0.05, 1.0]]))
VOL_S = 20.0
VOL_DELTA = 0.3  # band half-width


def vol_window():
    t = SPHERE.first_hit(VOL_O, VOL_D)
    assert np.all(np.isfinite(t))
    return t, float(t.min() - 0.3), float(t.max() + 0.3)


@functools.lru_cache(maxsize=None)
def exact_render(model, band=False):
    """render_exact (float64, stated error bound ≤ 1e-10) on the window, or per ray on its band."""
    t, t0, t1 = vol_window()
    if band:
        parts = [render_exact(SPHERE, SineColor(), model, VOL_S, VOL_O[i:i + 1], VOL_D[i:i + 1],
                              t[i] - VOL_DELTA, t[i] + VOL_DELTA) for i in range(len(t))]
        C, err = np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
    else:
        C, err = render_exact(SPHERE, SineColor(), model, VOL_S, VOL_O, VOL_D, t0, t1)
    assert err.max() <= 1e-10, err
    return C


def vol_error(backend, model, sampler, n, **knobs):
    """max |C − C_exact| over rays and channels for ``volume_<model>_<sampler>`` with N = n."""
    t, t0, t1 = vol_window()
    if sampler == "band":
        knobs.update(t_hit=t, delta=VOL_DELTA)
    r = run(backend, f"volume_{model}_{sampler}", SPHERE, VOL_O, VOL_D, t_min=t0, t_max=t1, n_samples=n,
            sharpness=VOL_S, color=SineColor(), **knobs)
    assert np.all(r.status == Status.CONVERGED), r.status_counts()
    return np.abs(r.outputs["color"] - exact_render(model, band=sampler == "band"))


def order(e_coarse, e_fine, ratio):
    """Observed convergence order between sample counts N and ratio·N."""
    return np.log(e_coarse / e_fine) / np.log(ratio)


@pytest.mark.parametrize("sampler", ["uniform", "band"])
@pytest.mark.parametrize("model", ["nerf", "volsdf", "neus"])
def test_volume_converges_to_render_exact_second_order(any_backend, model, sampler):
    """Equal bins with midpoint samples: the midpoint rule for ∫ T σ ρ dt (nerf, volsdf), and for
    NeuS exact per-bin opacity with ρ at the bin midpoint — both O(δ²) = O(N⁻²).  Measured on
    numpy (max error over 3 rays × 3 channels): N = 32 → 128: nerf 2.9e-4 → 1.8e-5, volsdf 3.8e-4 →
    2.0e-5, neus 4.3e-5 → 2.7e-6 (uniform); band about 2.5× smaller; orders 1.95–2.1."""
    e32, e128 = vol_error(any_backend, model, sampler, 32).max(), vol_error(any_backend, model, sampler, 128).max()
    assert 1.8 <= order(e32, e128, 4) <= 2.3, (e32, e128)
    assert e128 <= 3e-5, e128


@pytest.mark.parametrize("model", ["nerf", "volsdf", "neus"])
def test_volume_importance_converges_to_render_exact(any_backend, model):
    """Hierarchical sampling converges when the coarse pass is refined too (n_coarse = N): with
    n_coarse fixed, regions the coarse weights call unimportant keep the coarse resolution and the
    error stalls (measured: nerf 3.4e-4 at N = 16, 1.2e-4 at N = 256 with n_coarse = 16).  With
    n_coarse = N the grid is piecewise uniform with jumps at the coarse-bin edges, where a sample
    sits off its bin's centre: observed order ≈ 2 (numpy, N = 16 → 64: nerf 1.8, volsdf 2.0,
    neus 2.0)."""
    e16 = vol_error(any_backend, model, "importance", 16, n_coarse=16).max()
    e64 = vol_error(any_backend, model, "importance", 64, n_coarse=64).max()
    assert order(e16, e64, 4) >= 1.5, (e16, e64)
    assert e64 <= 5e-5, e64


@pytest.mark.parametrize("model", ["nerf", "volsdf", "neus"])
def test_volume_stratified_converges_to_render_exact(any_backend, model):
    """One uniform random point per bin: a zero-mean O(δ²) error per bin, independent across bins,
    so the RMS error is O(√N·δ²) = O(N^−1.5) (plus an O(N⁻²) bias from the nonlinearity of T).
    RMS over 8 seeds × 3 rays × 3 channels at N = 32 and 256 (expected ratio 8^1.5 ≈ 23; the
    RMS of ~50 effectively independent samples is good to ~15 %): numpy measured orders
    nerf 1.46, volsdf 1.44, neus 1.44 (RMS 7–9e-4 at N = 32, ~4e-5 at N = 256)."""
    rms = [np.sqrt(np.mean([vol_error(any_backend, model, "stratified", n, seed=k) ** 2 for k in range(8)]))
           for n in (32, 256)]
    assert 1.25 <= order(rms[0], rms[1], 8) <= 1.9, rms


@pytest.mark.parametrize("sampler", ["uniform", "band"])
def test_unisurf_is_reference_composite_on_the_same_samples(any_backend, sampler):
    """UNISURF has no continuous reference (occupancy is the discrete α): the renderer must equal
    reference.rendering.composite(occupancy_alpha(φ(x_i)), ρ(x_i)) on its own sample points —
    bin midpoints of [t_min, t_max] (uniform) or of [t̂ − Δ, t̂ + Δ] (band)."""
    from reference.rendering import composite, occupancy_alpha

    t, t0, t1 = vol_window()
    n, col = 40, SineColor(frequency=3.0)
    lo, hi = (t - VOL_DELTA, t + VOL_DELTA) if sampler == "band" else (np.full(3, t0), np.full(3, t1))
    ts = lo[:, None] + (hi - lo)[:, None] * (np.arange(n) + 0.5) / n
    x = VOL_O[:, None, :] + ts[..., None] * VOL_D[:, None, :]
    C, T_end = composite(occupancy_alpha(SPHERE.value(x, np), VOL_S, np), col.value(x, np), np)
    kw = dict(t_hit=t, delta=VOL_DELTA) if sampler == "band" else {}
    r = run(any_backend, f"volume_unisurf_{sampler}", SPHERE, VOL_O, VOL_D, t_min=t0, t_max=t1, n_samples=n,
            sharpness=VOL_S, color=col, **kw)
    np.testing.assert_allclose(r.outputs["color"], C, rtol=0, atol=1e-12)
    np.testing.assert_allclose(r.outputs["opacity"], 1 - T_end, rtol=0, atol=1e-12)


@pytest.mark.parametrize("color", [None, SineColor(frequency=5.0, phases=(0.3, -1.0, 2.5))])
def test_render_surface_is_colour_at_exact_hit(any_backend, color):
    o, d, t, hit, x = hits(SPHERE, 10)
    r = run(any_backend, "render_surface", SPHERE, o, d, color=color)
    assert np.all(r.status[hit] == Status.CONVERGED) and np.all(r.status[~hit] == Status.MISS)
    # |ρ(x̂_found) − ρ(x̂)| ≤ L_ρ |t_found − t|: the xtol = 1e-12 bracket gives ≤ ~1e-11
    rho = color or SineColor()
    np.testing.assert_allclose(r.outputs["color"][hit], rho.value(x[hit], np), atol=1e-9, rtol=0)
    assert np.all(r.outputs["color"][~hit] == 0)


def test_color_is_an_input_of_render_methods_only(any_backend):
    o, d, t, hit, x = hits(SPHERE, 3)
    assert {m for m, s in METHODS.items() if s.needs_color} == {m for m, s in METHODS.items() if s.family == "render"}
    kw = dict(t_max=6.0, n_samples=16)
    a = run(any_backend, "volume_nerf_uniform", SPHERE, o, d, **kw).outputs["color"]
    b = run(any_backend, "volume_nerf_uniform", SPHERE, o, d, color=SineColor(), **kw).outputs["color"]
    c = run(any_backend, "volume_nerf_uniform", SPHERE, o, d, color=SineColor(frequency=7.0), **kw).outputs["color"]
    np.testing.assert_array_equal(a, b)  # None means SineColor()
    assert np.abs(a - c).max() > 1e-3  # the field passed is the field used
    with pytest.raises(ValueError, match="does not shade"):
        run(any_backend, "sphere_trace", SPHERE, o, d, color=SineColor())
    with pytest.raises(ValueError, match="colour field"):
        run(any_backend, "render_surface", SPHERE, o, d, color=(1.0, 0.0, 0.0))


def test_neus_deep_inside_is_not_a_silent_nan(any_backend):
    # unit-ish sphere, s = 1000: φ ≈ −0.8 at the centre, sφ ≈ −800; the exact colour is finite
    o, d = np.array([[0.1, -0.2, -3.0]]), np.array([[0.0, 0.0, 1.0]])
    r = run(any_backend, "volume_neus_uniform", SPHERE, o, d, t_min=0.0, t_max=4.0, n_samples=64, sharpness=1000.0)
    assert not np.any(np.isnan(r.outputs["color"][r.status == Status.CONVERGED])), r.outputs["color"]


@pytest.mark.parametrize("sampler", ["uniform", "importance", "band"])
def test_early_termination_saves_work_and_bounds_the_change(any_backend, sampler):
    o, d, t, hit, x = hits(SPHERE, 6)
    kw = dict(n_samples=128, sharpness=50.0, t_min=0.0, t_max=6.0, t_hit=t if sampler == "band" else None)
    if sampler == "band":
        kw["delta"] = 0.5
    full = run(any_backend, f"volume_nerf_{sampler}", SPHERE, o, d, **kw)
    cut = run(any_backend, f"volume_nerf_{sampler}", SPHERE, o, d, t_threshold=1e-3, **kw)
    ok = full.status == Status.CONVERGED
    # the dropped tail weighs at most T < 1e-3 times max ρ (SineColor: ρ ≤ 1)
    assert np.abs(cut.outputs["color"][ok] - full.outputs["color"][ok]).max() <= 1e-3
    assert cut.outputs["work_saved"][ok & hit].min() > 0 and np.all(full.outputs["work_saved"][ok] == 0)
    assert np.all(cut.evals[ok] <= full.evals[ok]) and cut.evals.sum() < full.evals.sum()


def test_stratified_is_seeded_and_importance_beats_uniform(any_backend):
    o, d, t, hit, x = hits(SPHERE, 4)
    i = int(np.flatnonzero(hit)[0])
    o, d = o[i:i + 1], d[i:i + 1]
    kw = dict(t_min=1.0, t_max=4.0, sharpness=50.0)
    a = run(any_backend, "volume_nerf_stratified", SPHERE, o, d, n_samples=32, seed=3, **kw).outputs["color"]
    b = run(any_backend, "volume_nerf_stratified", SPHERE, o, d, n_samples=32, seed=3, **kw).outputs["color"]
    c = run(any_backend, "volume_nerf_stratified", SPHERE, o, d, n_samples=32, seed=4, **kw).outputs["color"]
    np.testing.assert_array_equal(a, b)
    assert np.any(a != c)
    exact = render_exact(SPHERE, SineColor(), "nerf", 50.0, o, d, 1.0, 4.0)[0][0]
    uni = run(any_backend, "volume_nerf_uniform", SPHERE, o, d, n_samples=64, **kw).outputs["color"][0]
    imp = run(any_backend, "volume_nerf_importance", SPHERE, o, d, n_samples=32, n_coarse=32, **kw).outputs["color"][0]
    assert np.abs(imp - exact).max() < np.abs(uni - exact).max()


def test_volume_needs_finite_t_max(any_backend):
    o, d = camera(2)
    with pytest.raises(ValueError, match="t_max"):
        run(any_backend, "volume_nerf_uniform", SPHERE, o, d, t_max=np.inf)


