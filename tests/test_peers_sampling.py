"""bench/studies/peers.py (the compiled and scipy peers of ``bench speed``) and bench/studies/sampling.py (samples
to a colour error target): small, fast cases."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from bench.studies import peers, sampling
from bench.studies.speed import scenes, unit_timer


def test_peers_skip_numba_cleanly_when_it_is_absent(monkeypatch):
    monkeypatch.setitem(sys.modules, "numba", None)  # `import numba` raises ImportError
    mod, why = peers.numba_or_reason()
    assert mod is None and "numba is not installed" in why
    runs, skipped = peers.root_peer_runs(scenes(8), repeats=1, t_max=10.0, unit_timer=unit_timer)
    assert len(skipped) == 1 and "numba per-ray sphere tracer: skipped: numba is not installed" in skipped[0]
    assert {label for _, label, _, _ in runs} == {"peer:scipy"}  # scipy's row still runs, on both scenes
    assert [name for name, *_ in runs] == list(scenes(8))


def test_numba_tracer_matches_the_scene_and_the_exact_hits():
    numba = pytest.importorskip("numba")
    from impls import Status

    for name, (scene, o, d) in scenes(16).items():
        peers.check_scalar_phi(name, scene)  # the hand-written φ is the scene's
        trace = peers.numba_tracer(numba, peers.SCALAR_PHI[name])
        n = o.shape[0]
        t, st, ev = np.empty(n), np.empty(n, np.int32), np.empty(n, np.int32)
        c, r = scene.bounding_sphere()
        trace(np.ascontiguousarray(o), np.ascontiguousarray(d), np.asarray(c, float), float(r), 0.0, 10.0, 1e-9, 4096,
              t, st, ev)
        exact = scene.first_hit(o, d, 0.0)
        hit = np.isfinite(exact)
        assert np.array_equal(st == Status.CONVERGED, hit), name  # no false hit or miss here
        assert np.all(np.isinf(t[~hit])) and np.all(ev[~hit] >= 0)
        # φ < 1e-9 bounds the depth error by 1e-9/|cos| at the hit
        assert np.max(np.abs(t[hit] - exact[hit])) <= 1e-6, name
    with pytest.raises(ValueError, match="differs"):
        peers.check_scalar_phi("sphere", scenes(2)["torus∪box"][0])


@pytest.mark.parametrize("lib", ["torch", "jax"])
def test_plain_compositing_is_the_backends_sum(lib):
    pytest.importorskip(lib)
    from impls import registry
    from reference.rendering import SineColor

    if lib == "jax":
        import jax

        jax.config.update("jax_enable_x64", True)
    for name, (scene, o, d) in scenes(6).items():
        p = registry.resolve("numpy").prepare("volume_nerf_uniform", scene, o, d, t_min=0.0, t_max=6.0, color=SineColor(),
                                              n_samples=40, sharpness=50.0, t_threshold=0.0)
        want = p.result(p.run()).outputs["color"]
        render = peers.plain_compositing(lib, name, 40, 0.0, 6.0, 50.0)
        if lib == "torch":
            import torch

            got = render(torch.as_tensor(o), torch.as_tensor(d)).numpy()
        else:
            import jax.numpy as jnp

            got = np.asarray(render(jnp.asarray(o), jnp.asarray(d)))
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12, err_msg=name)


def test_smallest_n_doubles_then_bisects():
    calls = []

    def err(n):
        calls.append(n)
        return 1.0 / n

    n, e, best = sampling.smallest_n(err, 1 / 100, n_min=4, n_max=4096)
    assert n == 100 and e <= 1 / 100 and calls[:6] == [4, 8, 16, 32, 64, 128]
    n, e, best = sampling.smallest_n(lambda n: 1.0 / n, 1e-6, n_min=4, n_max=64)
    assert n is None and np.isnan(e) and best == 1 / 64
    assert sampling.smallest_n(lambda n: 0.0, 1e-3)[0] == 4


def test_sampling_table_on_a_tiny_case_is_monotone_and_minimal():
    variants = (("uniform", "uniform", {}), ("band Δ=0.5", "band", {"delta": 0.5}))
    targets = (1e-1, 1e-2)
    df = sampling.sampling_table(["sphere.camera.64x64"], targets, variants=variants, max_rays=4, n_max=512)
    assert set(df["rays"]) == {"all", "hits"} and len(df) == 2 * 2 * 2
    errs = sampling.ColourErrors(__import__("reference.cases", fromlist=["get_case"]).get_case("sphere.camera.64x64"),
                                 max_rays=4)
    for (rays, label), g in df.groupby(["rays", "sampler"]):
        g = g.sort_values("target", ascending=False)
        ns = [n for n in g["N"] if n is not None and np.isfinite(n)]
        assert ns == sorted(ns), (rays, label, ns)  # a tighter target never needs fewer samples
        _, sampler, knobs = next(v for v in variants if v[0] == label)
        mask = errs.rays[rays]
        for _, r in g.iterrows():
            if r["N"] is None or not np.isfinite(r["N"]):
                assert r["best_error"] > r["target"]
                continue
            n = int(r["N"])
            assert r["error_at_N"] <= r["target"]
            assert np.max(errs(sampler, knobs, n)[mask]) == r["error_at_N"]
            if n > 4:  # minimal on the search path: one sample fewer misses the target
                assert np.max(errs(sampler, knobs, n - 1)[mask]) > r["target"]
    uni = df[df["sampler"] == "uniform"]
    assert np.all(uni["x_fewer_than_uniform"].dropna() == 1.0)
    # the table's own rendering and the report section it becomes
    md = sampling.markdown(df)
    assert md.count("\n") == 1 + 2 * 2 and "band Δ=0.5" in md


def test_report_section_reads_the_written_table(tmp_path):
    df = sampling.sampling_table(["sphere.camera.64x64"], (1e-1,), variants=sampling.VARIANTS[:1], max_rays=2, n_max=64)
    assert sampling.section_md(tmp_path) == []
    df.to_csv(tmp_path / sampling.FILE, index=False)
    lines = sampling.section_md(tmp_path)
    assert lines[0] == "## Samples to a colour error target" and "| sphere.camera.64x64 |" in lines[4]


def test_volume_rows_compare_every_renderer_with_numpy(monkeypatch):
    def no_compiler(lib):
        raise ImportError(f"{lib} not here (test)")

    monkeypatch.setattr(peers, "_compile_plain", no_compiler)
    rows, skipped = peers.volume_rows(["numpy"], scenes(4), n_samples=8, repeats=2)
    assert [r["scene"] for r in rows] == ["sphere", "torus∪box"]
    assert all(r["max_color_diff_vs_numpy"] == 0 and r["time_min_s"] <= r["time_s"] <= r["time_max_s"] for r in rows)
    assert skipped == ["plain torch compositing: skipped: torch not here (test)",
                       "plain jax compositing: skipped: jax not here (test)"]
    assert "torus∪box" in peers.format_volume(rows)
