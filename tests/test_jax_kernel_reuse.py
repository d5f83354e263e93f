"""The jax backend compiles one kernel per method and structure: knobs it can trace are runtime
arguments (:meth:`impls.jax.backend.JaxBackend.compile_configuration`), so a tolerance sweep
reuses one kernel, and a reused kernel gives exactly what a kernel compiled for the setting
gives, in float32 too (a traced knob is weakly typed, as the constant it replaces)."""

from __future__ import annotations

import numpy as np
import pytest

from impls import Status
from reference import Sphere
from tests.conftest import resolve_or_skip


def _rays(n=32):
    rng = np.random.default_rng(0)
    o = np.tile([0.0, 0.0, -3.0], (n, 1))
    d = np.column_stack([rng.uniform(-0.2, 0.2, n), rng.uniform(-0.2, 0.2, n), np.ones(n)])
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


def _result(backend, scene, o, d, dtype, **knobs):
    prep = backend.prepare("sphere_trace", scene, o, d, dtype=dtype, t_min=0.0, t_max=10.0, **knobs)
    return prep, prep.result(prep.run())


@pytest.mark.slow  # compiles jax kernels
@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_a_tolerance_sweep_reuses_one_kernel_with_the_results_of_its_own(dtype, monkeypatch):
    from impls.jax import backend as jb

    scene, (o, d) = Sphere(center=(0.0, 0.0, 0.0), radius=1.0), _rays()
    shared = resolve_or_skip("jax:cpu")
    first, _ = _result(shared, scene, o, d, dtype, tol=1e-6)
    second, got = _result(shared, scene, o, d, dtype, tol=1e-3)
    assert first.compile_cache in (None, "compiled", "reused") and second.compile_cache == "reused"
    # (the traced knob names and compiled-in knobs of each kernel, should there be more than one)
    assert len(shared._kernels) == 1, [(k[4], k[5]) for k in shared._kernels]
    # the setting compiled into a kernel of its own (no knob traced): the same rays, bit for bit
    monkeypatch.setattr(jb, "_traced_sets", lambda method, knobs: [()])
    _, want = _result(resolve_or_skip("jax:cpu"), scene, o, d, dtype, tol=1e-3)
    for k in ("t", "status", "iterations", "evals"):
        np.testing.assert_array_equal(getattr(got, k), getattr(want, k), err_msg=k)
    # and the setting matters: the other tolerance, through the same kernel, iterates differently
    assert (got.status == Status.CONVERGED).all()
    assert np.any(got.iterations != _result(shared, scene, o, d, dtype, tol=1e-6)[1].iterations)


@pytest.mark.slow  # compiles jax kernels
def test_a_different_structure_compiles_its_own_kernel():
    b = resolve_or_skip("jax:cpu")
    o, d = _rays()
    _result(b, Sphere(center=(0.0, 0.0, 0.0), radius=1.0), o, d, "float64")
    # a kernel of its own is a new entry of the backend's table (its compile_cache may still say
    # "reused": jax's persistent cache on disk can hold it from an earlier session)
    half = Sphere(center=(0.0, 0.0, 0.0), radius=0.5)
    _result(b, half, o, d, "float64")  # a parameter compiled in
    assert len(b._kernels) == 2
    _result(b, half, o[:16], d[:16], "float64")  # 16 rays: the same padded size (64 rows)
    assert len(b._kernels) == 2
    o2, d2 = _rays(100)  # another padded size (128 rows)
    _result(b, half, o2, d2, "float64")
    assert len(b._kernels) == 3
    _result(b, half, o, d, "float64", max_steps=64)  # a budget: a runtime argument (TRACEABLE_KNOBS)
    assert len(b._kernels) == 3
    _result(b, half, o, d, "float64", bounds=0)  # a switch between code paths, compiled in
    assert len(b._kernels) == 4


@pytest.mark.slow  # compiles jax kernels
@pytest.mark.parametrize("dtype", ["float32", "float64"])
@pytest.mark.parametrize("method", ["hybrid_secant", "sphere_trace", "march_newton"])
def test_depth_ranges_share_a_kernel_with_the_results_of_their_own(method, dtype, monkeypatch):
    """A root finder's depth range is a runtime argument (``RANGE_METHODS``): cases that differ in
    it alone (the stability stage's unit spheres) run one kernel, whose answers follow the range
    (a t_min past the entry finds the exit, a t_max before the hit misses), and a range gives, bit
    for bit, what a kernel with that range compiled in gives: a negative t_min (rays starting on a
    surface) with an infinite t_max, and a t_min inside the solid."""
    from impls.jax import backend as jb

    scene = Sphere(center=(0.0, 0.0, 0.0), radius=1.0)
    o, d = _rays()  # from z = −3 towards the unit sphere: entry at t ≈ 2, exit at t ≈ 4
    ranges = [(0.0, 10.0), (-1e-9, float("inf")), (3.0, 10.0), (0.0, 1.5)]
    shared = resolve_or_skip("jax:cpu")
    got = {}
    for r in ranges:
        prep = shared.prepare(method, scene, o, d, dtype=dtype, t_min=r[0], t_max=r[1])
        got[r] = prep.result(prep.run())
    assert len(shared._kernels) == 1, [k[4] for k in shared._kernels]
    exits = got[(3.0, 10.0)]  # every ray has one (float32 may flag some it cannot resolve)
    conv = exits.status == Status.CONVERGED
    assert conv.any() and (exits.t[conv] > 3.5).all() and not (exits.status == Status.MISS).any()
    assert (got[(0.0, 10.0)].t < 2.5).all() and (got[(0.0, 1.5)].status == Status.MISS).all()
    monkeypatch.setattr(jb, "RANGE_METHODS", frozenset())  # each range compiled in
    own = resolve_or_skip("jax:cpu")
    for r in ranges[1:3]:
        prep = own.prepare(method, scene, o, d, dtype=dtype, t_min=r[0], t_max=r[1])
        want = prep.result(prep.run())
        for k in ("t", "status", "iterations", "evals"):
            np.testing.assert_array_equal(getattr(got[r], k), getattr(want, k), err_msg=f"{r} {k}")
    assert len(own._kernels) == 2


def test_padded_sizes_are_powers_of_two_of_at_least_pad():
    from impls.jax.driver import padded_size

    assert [padded_size(n, 64) for n in (1, 63, 64, 65, 128, 129, 1000, 1 << 20)] == [64, 64, 64, 128, 128, 256,
                                                                                      1024, 1 << 20]
    assert [padded_size(n, 0) for n in (1, 37, 1000)] == [1, 37, 1000]
    assert padded_size(0, 64) == 0 and padded_size(5, 100) == 128


@pytest.mark.slow  # compiles jax kernels
@pytest.mark.parametrize("method", ["hybrid_secant", "sphere_trace", "march_newton", "render_surface", "curvature",
                                    "dt_implicit", "volume_neus_stratified", "volume_nerf_importance"])
def test_padding_rows_change_no_result(method):
    """A batch padded to a power of two (``MaskedSettings.pad``) gives, on its own rays, what the
    unpadded batch gives, and outputs of the rays' own length: bit for bit for root finders,
    shading and the t_hit methods (per-ray arithmetic); to 4 ulps (of the value, or of 1) for volume rendering, whose sums
    over a ray's samples XLA vectorises by the batch's shape, padded or not (without padding, the
    same 37 rays in a batch of 64 round 17 depths 1 ulp apart from a batch of 37)."""
    from reference.cases import get_case

    case = get_case("torus.camera.32x32")
    rays = np.arange(0, case.n_rays, 27)[:37]  # 37 rays across the image: hits, misses, grazing
    kw = {}
    if method in ("curvature", "dt_implicit"):  # at hits only
        rays = np.flatnonzero(np.isfinite(case.exact_t))[::7][:37]
        kw["t_hit"] = case.exact_t[rays]
    o, d = case.origins[rays], case.directions[rays]
    got = {}
    for pad in (64, 0):
        b = resolve_or_skip("jax:cpu")
        b.configure(pad=pad)
        prep = b.prepare(method, case.scene, o, d, t_min=case.t_min, t_max=case.t_max, **kw)
        out = prep.run()
        b.synchronize(out)
        got[pad] = prep.result(out)
    assert got[64].t.shape == (len(o),)
    # (opacity = 1 − transmittance: its rounding is 1's, so an absolute 4 ulps of 1 as well)
    rtol = 4 * np.finfo(np.float64).eps if method.startswith("volume_") else 0.0
    for k in ("status", "iterations", "evals"):
        np.testing.assert_array_equal(getattr(got[64], k), getattr(got[0], k), err_msg=k)
    np.testing.assert_allclose(got[64].t, got[0].t, rtol=rtol, atol=rtol, err_msg="t")
    assert got[64].outputs.keys() == got[0].outputs.keys()
    for k, v in got[0].outputs.items():
        assert np.shape(got[64].outputs[k]) == np.shape(v), k
        np.testing.assert_allclose(got[64].outputs[k], v, rtol=rtol, atol=rtol, err_msg=k)


@pytest.mark.slow  # traces every jax method once per number knob
def test_the_declared_traceable_knobs_are_exactly_those_that_trace(monkeypatch):
    """``TRACEABLE_KNOBS`` (the knobs a method's kernel takes at run time, so that a sweep over
    them reuses one kernel) lists every method of the jax backend, with exactly the number knobs
    that trace on their own; and they trace together."""
    import jax

    from impls.jax import backend as jb
    from impls.methods import METHODS
    from reference.cases import get_case

    b = resolve_or_skip("jax:cpu")
    monkeypatch.setattr(jb.JaxBackend, "compile", lambda self, fn, *args: (jax.eval_shape(fn, *args), 0.0))

    def lowered_only(self, traced):
        # traced and lowered, not compiled: XLA's compile (about 1 s a kernel, 63 of the test's 70 s)
        # tells nothing about tracing.  A part kernel whose outputs the next part is traced on
        # (render_surface's) answers zeros of its output shapes.
        traced.lower()
        return lambda *args: jax.tree.map(lambda s: jax.numpy.zeros(s.shape, s.dtype), traced.out_info)

    monkeypatch.setattr(jb.JaxBackend, "_compile_traced", lowered_only)
    monkeypatch.setattr(b, "_store", None)  # (nothing of these stand-ins is stored, nothing stored is loaded)
    case = get_case("sphere.camera.64x64")
    o, d = case.origins[:8], case.directions[:8]

    def traces(method, names, kw):
        monkeypatch.setattr(jb, "_traced_sets", lambda m, knobs: [names])
        b._kernels.clear()
        jb._TRACED_FAILED.clear()
        try:
            b.prepare(method, case.scene, o, d, t_min=case.t_min, t_max=case.t_max, **kw)
        except AssertionError:  # the only set offered failed to trace
            return False
        return True

    for method in b.methods():
        spec = METHODS[method]
        kw = {"t_hit": np.full(len(o), 2.0)} if spec.needs_t_hit else {}
        nums = [k.name for k in spec.knobs if isinstance(k.default, (int, float)) and not isinstance(k.default, bool)]
        nums += list(jb.RANGE_KNOBS) if method in jb.RANGE_METHODS else []  # the depth range, as two knobs
        alone = tuple(sorted(k for k in nums if traces(method, (k,), kw)))
        assert alone == tuple(sorted(jb.TRACEABLE_KNOBS[method])), method
        assert traces(method, alone, kw), method


def test_knob_sets_start_from_the_declaration_and_fall_back_to_floats():
    """A catalog method tries its declared traceable knobs first; a method without a declaration
    (a user's) tries every number knob, then the floats, then its first knob if a float, then none."""
    pytest.importorskip("jax")
    from impls.jax import backend as jb

    knobs = {"xtol": 1e-8, "bounds": 1, "max_steps": 64, "reach": 0.1, "ladder": -1, "ladder_after": 64}
    sets = jb._traced_sets("hybrid_secant", knobs)
    assert sets[0] == ("ladder_after", "max_steps", "reach", "xtol") and sets[-1] == ()
    assert all(k not in s for s in sets for k in ("bounds", "ladder"))
    user = {"tol": 1e-6, "n": 8, "gain": 0.5}
    assert jb._traced_sets("users_method", user) == [("gain", "n", "tol"), ("gain", "tol"), ("tol",), ()]


@pytest.mark.slow  # compiles jax kernels
@pytest.mark.parametrize("n", [32, 100])  # 100 rays: padded to 128 rows, the outputs cut back
def test_render_surface_shades_the_hybrid_kernels_hit_with_the_fused_kernels_results(n, monkeypatch):
    """render_surface runs hybrid_secant's own kernel (one compilation for both methods) and a
    shading kernel given its output; its outputs equal, bit for bit, those of one kernel that
    finds the hit and shades it."""
    from impls.core import rendering
    from impls.jax.backend import JaxBackend

    resolve_or_skip("jax:cpu")
    scene, (o, d) = Sphere(center=(0.0, 0.0, 0.0), radius=0.75), _rays(n)
    b = JaxBackend("cpu")
    b._store = None
    kw = dict(dtype="float64", t_min=0.0, t_max=10.0, xtol=1e-10)
    b.prepare("hybrid_secant", scene, o, d, **kw)
    hybrid = set(b._kernels)
    prep = b.prepare("render_surface", scene, o, d, **kw)
    added = set(b._kernels) - hybrid
    assert [k[0] for k in added] == ["render_surface"]  # the hit's kernel was hybrid_secant's
    got = prep.result(prep.run())
    monkeypatch.setattr(rendering.render_surface, "hit_method", None)
    fused = JaxBackend("cpu")
    fused._store = None
    want_prep = fused.prepare("render_surface", scene, o, d, **kw)
    assert [k[0] for k in fused._kernels] == ["render_surface"]
    want = want_prep.result(want_prep.run())
    assert got.t.shape == (n,) and got.outputs["color"].shape == (n, 3)
    assert (got.status == Status.CONVERGED).any() and (got.status == Status.MISS).any()
    for k in ("t", "status", "iterations", "evals"):
        np.testing.assert_array_equal(getattr(got, k), getattr(want, k), err_msg=k)
    np.testing.assert_array_equal(got.outputs["color"], want.outputs["color"])


def test_a_precomputed_hit_is_refused_with_a_callers_theta():
    from impls.core import rendering

    with pytest.raises(ValueError, match="precomputed hit"):
        rendering.render_surface(resolve_or_skip("numpy"), Sphere(center=(0.0, 0.0, 0.0), radius=1.0), None, None,
                                 t_min=0.0, t_max=1.0, t_hit=None, color=None, theta=np.zeros(4), hit={})


@pytest.mark.slow  # compiles jax kernels
def test_volume_renderers_share_a_sampler_kernel_and_a_shading_kernel_with_the_fused_results(monkeypatch):
    """The volume renderers whose bins are fixed up front run a sampler kernel (one per sampler,
    whatever the density model) and a shading kernel (one per model, or for the three of
    ``SAMPLE_DENSITIES`` one for all, whatever the sampler); their
    statuses and counts equal those of one kernel per method, and their floats are equal to a few
    units in the last place (XLA contracts a multiply and an add into one FMA where both are in
    one fused loop, so where the bins are computed, in their own kernel or inside the shading's,
    can move a sample by one rounding)."""
    from impls.core.table import METHOD_TABLE
    from impls.jax.backend import JaxBackend

    resolve_or_skip("jax:cpu")
    scene, (o, d) = Sphere(center=(0.0, 0.0, 0.0), radius=0.75), _rays(100)
    t_hit = np.full(len(o), 2.5)
    b = JaxBackend("cpu")
    b._store = None
    methods = [f"volume_{m}_{s}" for m in ("nerf", "neus") for s in ("uniform", "stratified", "band")]

    def run(backend, method):
        kw = dict(dtype="float64", t_min=0.0, t_max=6.0, n_samples=24, sharpness=20.0)
        if method.endswith("band"):
            kw.update(t_hit=t_hit, delta=0.3)
        prep = backend.prepare(method, scene, o, d, **kw)
        return prep.result(prep.run())

    got = {m: run(b, m) for m in methods}
    assert sorted(k[0] for k in b._kernels) == sorted(
        ["volume_samples_uniform", "volume_samples_stratified", "volume_samples_band", "volume_shading_switch",
         "volume_shading_neus"])  # (nerf's shading: the kernel of the three sample-density models)
    for m in methods:
        monkeypatch.delattr(METHOD_TABLE[m], "stages")
    fused = JaxBackend("cpu")
    fused._store = None
    for m in methods:
        want = run(fused, m)
        assert got[m].t.shape == (100,) and (got[m].status == Status.CONVERGED).any()
        for k in ("status", "iterations", "evals"):
            np.testing.assert_array_equal(getattr(got[m], k), getattr(want, k), err_msg=f"{m} {k}")
        assert set(got[m].outputs) == set(want.outputs)
        for k, a, w in [("t", got[m].t, want.t), *((k, got[m].outputs[k], want.outputs[k]) for k in want.outputs)]:
            a, w = np.asarray(a, dtype=np.float64), np.asarray(w, dtype=np.float64)
            finite = np.isfinite(w)
            np.testing.assert_array_equal(a[~finite], w[~finite], err_msg=f"{m} {k}")
            np.testing.assert_array_max_ulp(a[finite], w[finite], maxulp=4)  # 3 measured (neus, band)
    assert sorted(k[0] for k in fused._kernels) == sorted(methods)


@pytest.mark.slow  # compiles jax kernels
@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_three_density_models_share_one_kernel_with_the_results_of_their_own(dtype, monkeypatch):
    """nerf, volsdf and unisurf (``SAMPLE_DENSITIES``: opacities from φ at the samples) run one
    shading kernel and one importance-sampling kernel, the model a traced index (``lax.switch``):
    each model's outputs equal, bit for bit, those of a kernel compiled for that model alone, on
    128 rows of a torus and (float64) of a neural field, whose φ XLA cannot fold; the band sampler
    reuses the uniform one's shading kernel; and the model matters (three models, three colours)."""
    from impls.jax.backend import JaxBackend
    from reference.cases import get_case

    resolve_or_skip("jax:cpu")
    merged, alone = JaxBackend("cpu"), JaxBackend("cpu")
    merged._store = alone._store = None
    monkeypatch.setattr(alone, "_density_choice", lambda method, impl: None)  # a kernel per model
    for case_id in ("torus.camera.32x32",) + (("mlp.camera.32x32",) if dtype == "float64" else ()):
        case = get_case(case_id)
        o, d = case.origins[::9], case.directions[::9]  # 114 rays: 128 rows, padded
        merged._kernels.clear()
        for sampler, more in (("uniform", {}), ("importance", {"n_coarse": 8}),
                              ("band", {"delta": 0.2, "t_hit": np.full(len(o), 2.5)})):
            colors = []
            for model in ("nerf", "volsdf", "unisurf"):
                kw = dict(dtype=dtype, t_min=case.t_min, t_max=case.t_max, n_samples=16, sharpness=30.0, **more)
                got, want = (b.prepare(f"volume_{model}_{sampler}", case.scene, o, d, **kw) for b in (merged, alone))
                got, want = got.result(got.run()), want.result(want.run())
                for k in ("t", "status", "iterations", "evals"):
                    np.testing.assert_array_equal(getattr(got, k), getattr(want, k), err_msg=f"{model} {sampler} {k}")
                assert set(got.outputs) == set(want.outputs)
                for k in want.outputs:
                    np.testing.assert_array_equal(got.outputs[k], want.outputs[k], err_msg=f"{model} {sampler} {k}")
                colors.append(got.outputs["color"])
            assert not np.array_equal(colors[0], colors[1]) and not np.array_equal(colors[1], colors[2])
        assert sorted(k[0] for k in merged._kernels) == ["volume_samples_band", "volume_samples_uniform",
                                                         "volume_shading_switch", "volume_switch_importance"]


@pytest.mark.slow  # compiles jax kernels
@pytest.mark.parametrize("settings", ["timed", "untimed", "chunks", "ladder"])
def test_the_bisection_and_secant_marchers_share_one_kernel_with_the_results_of_their_own(settings, monkeypatch):
    """``march_bisect`` and ``march_secant`` run one kernel (``march_switch``: the secant's search,
    then the refinement the traced index picks), whose outputs equal, bit for bit, those of each
    method's own kernel: on a CSG camera and a torus camera (hits, misses, and rays that graze
    the surface and end UNCERTIFIED) with the levels of a timed run; on one of them with the one
    level of an untimed run, with chunks of 256 rows whose stragglers finish together (the
    refinement runs in both passes), and with ladder steps (a bracket found by the ladder stage)."""
    from impls.jax import driver
    from impls.jax.backend import JaxBackend
    from reference.cases import get_case

    resolve_or_skip("jax:cpu")
    st = {"timed": driver.MaskedSettings(), "untimed": driver.MaskedSettings(last=driver.CHUNK),
          "chunks": driver.MaskedSettings(chunk=256, tail_cap=16), "ladder": driver.MaskedSettings()}[settings]
    ladder = {"ladder": 8, "ladder_after": 4} if settings == "ladder" else {}
    merged, alone = JaxBackend("cpu", st), JaxBackend("cpu", st)
    merged._store = alone._store = None
    monkeypatch.setattr(alone, "_refiner_choice", lambda method, impl, th: None)  # a kernel per method
    cases = {"timed": ("csg.union.camera.32x32", "torus.camera.32x32"), "chunks": ("torus.camera.32x32",)}
    for case_id in cases.get(settings, ("csg.union.camera.32x32",)):
        case = get_case(case_id)
        o, d = (case.origins[::2], case.directions[::2]) if settings != "chunks" else (case.origins, case.directions)
        merged._kernels.clear()
        iterations = []
        for method in ("march_bisect", "march_secant"):
            kw = dict(t_min=case.t_min, t_max=case.t_max, xtol=1e-9, **ladder)
            got, want = (b.prepare(method, case.scene, o, d, **kw) for b in (merged, alone))
            got, want = got.result(got.run()), want.result(want.run())
            for k in ("t", "status", "iterations", "evals"):
                np.testing.assert_array_equal(getattr(got, k), getattr(want, k), err_msg=f"{case_id} {method} {k}")
            assert (got.status == Status.CONVERGED).sum() > len(o) // 4 and (got.status == Status.MISS).any()
            iterations.append(got.iterations)
        assert [k[0] for k in merged._kernels] == ["march_switch"]
        assert not np.array_equal(iterations[0], iterations[1])  # the refiner matters


def test_later_stages_must_follow_the_search_they_finish():
    """``run_loop``'s ``later`` (another algorithm's refinement after this one's search) refuses
    algorithms whose stages differ, a refiner with derivatives, and a driver without ``park``."""
    pytest.importorskip("jax")
    from impls.jax import driver
    from impls.methods import get_method

    scene = Sphere(center=(0.0, 0.0, 0.0), radius=1.0)

    def alg(method, **knobs):
        return get_method(method).algorithm(scene, 0.0, 10.0, get_method(method).validate(knobs), None, ladder=0)

    bisect, secant = alg("march_bisect"), alg("march_secant")
    driver.check_later(secant, [bisect, secant], park=True)
    with pytest.raises(ValueError, match="park"):
        driver.check_later(secant, [bisect, secant], park=False)
    with pytest.raises(ValueError, match="derivative"):
        driver.check_later(secant, [alg("march_newton")], park=True)
    with pytest.raises(ValueError, match="stages"):
        driver.check_later(secant, [alg("march_bisect", ladder=8)], park=True)
    with pytest.raises(ValueError, match="stages"):
        driver.check_later(secant, [alg("sphere_trace")], park=True)


def test_a_switched_renderer_is_the_renderer_of_the_model_it_picks():
    """The renderers of the model ``switch`` (``rendering.SWITCHED``: the density model an index,
    the knob ``density``) give each model's own outputs on a backend that picks the branch in
    Python (numpy), and refuse to run without the index."""
    from impls.core import rendering

    numpy = resolve_or_skip("numpy")
    scene, (o, d) = Sphere(center=(0.0, 0.0, 0.0), radius=0.75), _rays(16)
    kw = dict(t_min=0.0, t_max=6.0, t_hit=None, color=rendering.R.SineColor(), n_samples=12, sharpness=20.0,
              t_threshold=0.0)
    for i, model in enumerate(rendering.SAMPLE_DENSITIES):
        for sampler, more in (("uniform", {}), ("importance", {"n_coarse": 8}), ("stratified", {"seed": 3})):
            got = rendering.SWITCHED[sampler](numpy, scene, o, d, density=i, **kw, **more)
            want = rendering.IMPLS[f"volume_{model}_{sampler}"](numpy, scene, o, d, **kw, **more)
            for k in want:
                np.testing.assert_array_equal(got[k], want[k], err_msg=f"{model} {sampler} {k}")
    with pytest.raises(TypeError, match="density"):
        rendering.SWITCHED["importance"](numpy, scene, o, d, **kw, n_coarse=8)


@pytest.mark.slow  # compiles jax kernels
@pytest.mark.parametrize("fused", [False, True], ids=["sampler-kernel", "fused-kernel"])
def test_stratified_offsets_are_an_input_of_the_kernel_not_constants_of_it(fused, monkeypatch):
    """The stratified sampler's offsets (numpy's PCG64 draws, rays × samples floats) enter the
    jax kernel as an input drawn at every call, not as constants compiled into it: the seeds
    share one kernel (constants made a kernel per seed, 134 MB of constants each at 512² rays ×
    64 samples), and each seed gives numpy's colours, on the sampler kernel of the CPU and on the
    one fused kernel of a GPU.  100 rays: the kernel runs 128 rows, the padding rows' draws too."""
    from impls.core.table import METHOD_TABLE
    from impls.jax.backend import JaxBackend

    resolve_or_skip("jax:cpu")
    if fused:
        monkeypatch.delattr(METHOD_TABLE["volume_nerf_stratified"], "stages")
    scene, (o, d) = Sphere(center=(0.0, 0.0, 0.0), radius=0.75), _rays(100)
    b = JaxBackend("cpu")
    b._store = None
    numpy = resolve_or_skip("numpy")
    kw = dict(dtype="float64", t_min=0.0, t_max=6.0, n_samples=24, sharpness=20.0)
    got = {}
    for seed in (0, 1, 2):
        prep = b.prepare("volume_nerf_stratified", scene, o, d, seed=seed, **kw)
        got[seed] = prep.result(prep.run())
        want = numpy.prepare("volume_nerf_stratified", scene, o, d, seed=seed, **kw)
        want = want.result(want.run())
        np.testing.assert_array_equal(got[seed].status, want.status)
        np.testing.assert_allclose(got[seed].outputs["color"], want.outputs["color"], rtol=1e-12, atol=1e-15)
        again = prep.result(prep.run())  # the next call draws the same offsets
        np.testing.assert_array_equal(again.outputs["color"], got[seed].outputs["color"])
    assert [k[0] for k in b._kernels] == (["volume_nerf_stratified"] if fused
                                          else ["volume_samples_stratified", "volume_shading_switch"])
    # the draws matter: another seed, other colours
    assert np.abs(got[0].outputs["color"] - got[1].outputs["color"]).max() > 1e-3
