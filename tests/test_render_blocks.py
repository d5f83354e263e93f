"""The volume renderers shade their rays in blocks of at most ``BLOCK_SAMPLES`` samples
(:meth:`impls.base.ArrayBackend.map_rays`), so their memory is bounded by the block, not by the
number of rays: unblocked, the importance sampler on 256² rays of the neural SDF took 5.4 GB in
numpy and 6.6 GB in jax, and a 1024² camera sixteen times that.  A ray's outputs do not depend on
the block it was shaded in."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from impls.core import rendering
from reference import rays
from reference.cases import get_case
from reference.rendering import SineColor
from tests.conftest import require_method

VOLUME = [f"volume_{m}_{s}" for m in ("nerf", "volsdf", "unisurf", "neus")
          for s in ("uniform", "stratified", "band", "importance")]
CASE = get_case("torus.camera.32x32")


def _rays(side: int):
    """A camera on the torus with rays that hit, rays that miss and two bad rays (a NaN origin, a
    NaN direction: ``prepare`` makes a zero direction NaN)."""
    o, d = rays.pinhole(eye=(0.3, 1.4, 2.6), look_at=(0, 0, 0), up=(0, 1, 0), fov_deg=60, width=side, height=side)
    o, d = o.copy(), d.copy()
    o[3] = np.nan
    d[7] = np.nan
    return o, d


def _hits(o, d):
    """The exact first hits, NaN on the bad rays."""
    bad = ~(np.isfinite(o).all(axis=1) & np.isfinite(d).all(axis=1))
    t = CASE.scene.first_hit(np.where(bad[:, None], 0.0, o), np.where(bad[:, None], [[0.0, 0.0, 1.0]], d),
                             t_min=CASE.t_min)
    return np.where(bad, np.nan, t)


def _render(backend, method, o, d, t_hit, **knobs):
    """``method``'s implementation called on the backend's arrays (jax: under ``jax.jit``, a
    program traced afresh, so that no kernel of another block size is reused), as numpy."""
    impl = backend._impl[method]
    args = [backend.asarray(a, "float64") for a in (o, d, t_hit)]

    def call(o, d, t_hit):
        return impl(backend, CASE.scene, o, d, t_min=CASE.t_min, t_max=CASE.t_max, t_hit=t_hit, color=SineColor(),
                    **knobs)

    if backend.lib == "jax":
        import jax

        out = jax.jit(call)(*args)
    else:
        out = call(*args)
    return {k: backend.to_numpy(v) for k, v in out.items()}


def _knobs(method, n_samples, sharpness, t_threshold, *, delta=0.1, seed=3, n_coarse=16) -> dict:
    """``method``'s knobs: the shared ones, and the one its sampler adds (band: ``delta``,
    stratified: ``seed``, importance: ``n_coarse``)."""
    knobs = {"n_samples": n_samples, "sharpness": sharpness, "t_threshold": t_threshold}
    extra = {"band": {"delta": delta}, "stratified": {"seed": seed}, "importance": {"n_coarse": n_coarse}}
    return {**knobs, **extra.get(method.rsplit("_", 1)[1], {})}


@pytest.mark.parametrize("method", VOLUME)
def test_a_rays_outputs_do_not_depend_on_its_block(backend, method, monkeypatch):
    """Blocks of 1–8 and of 16–64 rays against one block of all 400 (early termination on, so that the
    eager backends' compaction runs inside blocks, and band rays without a hit): every output equal
    (jax: to 1e-12, its rounding, below)."""
    require_method(backend, method)
    o, d = _rays(20)
    t_hit = _hits(o, d)
    knobs = _knobs(method, 24, 30.0, 0.2)
    whole = _render(backend, method, o, d, t_hit, **knobs)
    # blocks of 8 (uniform, stratified, band), 2 (NeuS: φ at the edges too) or 1 ray (importance),
    # then of 64, 32 or 16 rays
    for block in (8 * 24, 100 * 24):
        monkeypatch.setattr(rendering, "BLOCK_SAMPLES", block)
        blocked = _render(backend, method, o, d, t_hit, **knobs)
        for k, v in whole.items():
            msg = f"{method} {k}, blocks of {block} samples"
            if backend.lib == "jax" and v.dtype.kind == "f":
                # XLA fuses and vectorises by the arrays' shapes, so a block rounds its sums and
                # products differently from the whole batch, in the last bits; NeuS's
                # α = (Φ(a) − Φ(b))/Φ(a) amplifies that by its cancellation (measured: 2e-14 at a
                # colour of 0.03).  1e-12 is four decades below the finest error the harness
                # judges a renderer at (1e-8)
                np.testing.assert_allclose(blocked[k], v, rtol=1e-12, atol=1e-15, err_msg=msg)
            else:
                np.testing.assert_array_equal(blocked[k], v, err_msg=msg)
    assert np.isnan(whole["color"][3]).all() and np.isnan(whole["color"][7]).all()
    assert (whole["status"] == 0).sum() > 100


@pytest.mark.parametrize("method", ["volume_neus_uniform", "volume_nerf_stratified", "volume_nerf_importance"])
def test_numpys_memory_is_bounded_by_the_block_not_the_rays(method, monkeypatch):
    """numpy's allocations (traced by tracemalloc) peak at a block's worth: 64² rays in blocks of
    2¹⁴ samples take less than a quarter of what they take in one block, the samples included
    (the bins, their points and the stratified draws are made block by block too)."""
    from impls.numpy.backend import NumpyBackend

    backend = NumpyBackend()
    o, d = _rays(64)
    t_hit = _hits(o, d)
    knobs = _knobs(method, 64, 50.0, 0.0, seed=5, n_coarse=32)

    def peak(block):
        monkeypatch.setattr(rendering, "BLOCK_SAMPLES", block)
        tracemalloc.start()
        try:
            out = _render(backend, method, o, d, t_hit, **knobs)
            return tracemalloc.get_traced_memory()[1], out
        finally:
            tracemalloc.stop()

    whole, a = peak(1 << 30)
    blocked, b = peak(1 << 14)
    assert blocked < whole / 4, (blocked, whole)
    np.testing.assert_array_equal(a["color"], b["color"])


@pytest.mark.slow  # compiles jax kernels
@pytest.mark.parametrize("method", ["volume_nerf_uniform", "volume_neus_stratified", "volume_volsdf_band"])
def test_jax_runs_its_sampler_and_shading_kernels_block_by_block(method, monkeypatch):
    """On the CPU a jax volume renderer whose bins are fixed up front is a sampler kernel and a
    shading kernel (:meth:`impls.jax.backend.JaxBackend.compile_configuration`); for more rays than
    a block both are compiled for a block and run block by block, so the bins one hands the other
    are a block's, not the camera's: the kernels take a block's rows, and the outputs are those of
    one block of all rays (to jax's rounding, as above)."""
    from impls.jax.backend import JaxBackend
    from tests.conftest import resolve_or_skip

    resolve_or_skip("jax:cpu")
    o, d = _rays(20)  # 400 rays: 512 rows padded
    knobs = _knobs(method, 24, 30.0, 0.2)
    if method.endswith("band"):
        knobs["t_hit"] = _hits(o, d)

    def run(block):
        monkeypatch.setattr(rendering, "BLOCK_SAMPLES", block)
        b = JaxBackend("cpu")
        b._store = None
        prep = b.prepare(method, CASE.scene, o, d, dtype="float64", t_min=CASE.t_min, t_max=CASE.t_max, **knobs)
        return {key[-3][0][0] for key in b._kernels}, prep.result(prep.run())  # the rays' rows of each kernel

    rows_whole, whole = run(1 << 30)
    rows_blocked, blocked = run(64 * 24)
    assert rows_whole == {512}
    assert rows_blocked == {rendering.shading_rows(method.split("_")[1], 24)} == ({16} if "neus" in method else {64})
    np.testing.assert_array_equal(blocked.status, whole.status)
    for k in ("color", "opacity", "samples_used"):
        np.testing.assert_allclose(blocked.outputs[k], whole.outputs[k], rtol=1e-12, atol=1e-15, err_msg=k)
    assert (whole.status == 0).sum() > 100
