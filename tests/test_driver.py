"""The compacting loop driver (impls.core.driver): per-ray results do not depend on the block
size, the straggler pool or the number of worker threads."""

import numpy as np
import pytest

from impls import registry
from impls.methods import METHODS
from reference.cases import get_case


def make_root_finder(method, scene, t_min, t_max, knobs, ladder=16):
    return METHODS[method].algorithm(scene, t_min, t_max, METHODS[method].validate(knobs), ladder=ladder)


def _backend_loop(name):
    if name == "torch":
        pytest.importorskip("torch")
    b = registry.resolve(name if name == "numpy" else f"{name}:cpu")

    def run(alg, o, d, scene, block, pool, workers):
        b.configure(block=block, pool=pool, threads=workers)
        out = b.run_loop(alg, b.asarray(o, "float64"), b.asarray(d, "float64"), b.ray_eval(scene))
        return {k: b.to_numpy(v) for k, v in out.items()}

    return run


@pytest.mark.parametrize("backend", ["numpy", "torch"])
@pytest.mark.parametrize("method", ["sphere_trace", "hybrid_secant", "march_secant"])
def test_results_do_not_depend_on_blocks_pool_or_threads(backend, method):
    case = get_case("csg.union.camera.32x32")
    knobs = {k.name: k.default for k in METHODS[method].knobs}
    if method != "sphere_trace":
        knobs["ladder_after"] = 8  # the ladder stage, and rays skipping it (0 → 2), on many rays
    alg = make_root_finder(method, case.scene, 0.0, 10.0, knobs)
    loop = _backend_loop(backend)
    ref = loop(alg, case.origins, case.directions, case.scene, block=1 << 16, pool=0, workers=1)
    assert (ref["iterations"] > 12).any()  # stragglers exist, so the pool is exercised
    if method != "sphere_trace":  # and ladder steps: their samples differ from single steps' (or are
        # evaluated past the pair a ray stops at), so the evaluations differ from a run without them
        plain = loop(make_root_finder(method, case.scene, 0.0, 10.0, knobs, ladder=0), case.origins, case.directions,
                     case.scene, block=1 << 16, pool=0, workers=1)
        assert (ref["evals"] != plain["evals"]).any()
    for block, pool, workers in ((100, 30, 1), (100, 30, 2), (37, 200, 3), (1 << 16, 4096, 2)):
        got = loop(alg, case.origins, case.directions, case.scene, block=block, pool=pool, workers=workers)
        for k in ("status", "iterations", "evals"):
            np.testing.assert_array_equal(got[k], ref[k], err_msg=f"{k}: block={block} pool={pool} workers={workers}")
        np.testing.assert_array_equal(got["t"], ref["t"])


@pytest.mark.parametrize("backend_id", ["numpy", "torch:cpu", "jax:cpu"])
def test_driver_settings_are_validated_and_recorded(backend_id):
    """Driver settings are one explicit configuration per backend: changed by ``configure``,
    checked (whole numbers, known names), and recorded as a plain dict."""
    b = registry.resolve(backend_id)
    if isinstance(b, registry.Unavailable):
        pytest.skip(b.reason)
    rec = b.settings.record()
    assert rec["driver"] in ("compacting", "masked") and rec["ladder"] == b.settings.ladder
    name = "threads" if "threads" in rec else "chunk"
    b.configure(**{name: 2})
    assert b.settings.record()[name] == 2
    for bad in (0, 1.5, True, "2"):
        with pytest.raises(ValueError, match=name):
            b.configure(**{name: bad})
    with pytest.raises(ValueError, match="no_such_setting"):
        b.configure(no_such_setting=1)


@pytest.mark.slow  # compiles many kernels or sweeps a whole catalog
@pytest.mark.parametrize("method", ["sphere_trace", "hybrid_secant", "march_newton", "march_bisect"])
def test_jax_results_do_not_depend_on_chunks_or_levels(method):
    """The jax driver (impls.jax.driver.run_loop: chunks, batches compacted level by level,
    the chunks' capped stragglers finished together) gives the same per-ray results for any
    chunk size, shrink ratio, last size and cap, including a single uncompacted level, with the
    refinement stages in every level or run once per chunk after them (``park``)."""
    pytest.importorskip("jax")
    import jax
    import jax.numpy as jnp

    from impls.jax import derivatives
    from impls.jax import driver as tracing

    registry.resolve("jax:cpu")  # float64 on
    # the torus camera: grazing rays take 36-512 steps, most rays a few (the torus ∪ box costs
    # ~30 % more compile per level and exercises no other driver path)
    case = get_case("torus.camera.32x32")
    o, d = case.origins, case.directions
    knobs = {k.name: k.default for k in METHODS[method].knobs}
    if method != "sphere_trace":
        knobs["ladder_after"] = 8  # ladder steps in the masked loops and the straggler pass
    alg = make_root_finder(method, case.scene, 0.0, 10.0, knobs)
    ev = derivatives.ray_eval(case.scene)

    def run(chunk, ratio, last, cap=1, park=True):
        f = jax.jit(lambda o, d: tracing.run_loop(alg, o, d, ev, chunk=chunk, ratio=ratio, last=last, tail_cap=cap,
                                                  park=park))
        return {k: np.asarray(v) for k, v in f(jnp.asarray(o), jnp.asarray(d)).items()}

    n = o.shape[0]
    ref = run(n, 2, n)  # one chunk, one level: every ray stepped until the last one is done
    assert (ref["iterations"] > 12).any() and (ref["iterations"] < 5).any()  # levels really compact
    if method != "sphere_trace":
        assert (ref["evals"] > ref["iterations"] + 1).any()  # ladder steps taken
    # chunks: whole, with padding (350: not dividing n), tiny (8 of them); ratios 3, 8, 32 (2:
    # level_sizes below); last level sizes 1 to 40; caps from 1 step (every straggler handed on) to
    # none reached.  Every level is a copy of the stage loops in the compiled program, and compile
    # time grows with their number (~1.5–3 s per level on a 2-core machine), the code paths do not:
    # 2-3 levels per setting, chunks' and stragglers' passes together
    # (impls.jax.driver.level_sizes).  (A fourth setting, whole chunks at ratio 8 down to 4 rays,
    # added 4 levels and no path: 154 s → 123 s for the three methods, empty cache, 2-core machine.)
    # (park: the hybrid's and the constant-step marches' refinement once per chunk after the levels,
    # or in every level; Newton's and sphere tracing's keep the levels either way: search_stages)
    for chunk, ratio, last, cap, park in ((n, 32, 1, 30, True), (350, 3, 40, 1, False), (128, 8, 16, 1000, True)):
        got = run(chunk, ratio, last, cap, park)
        for k in ("status", "iterations", "evals"):
            np.testing.assert_array_equal(got[k], ref[k], err_msg=f"{k}: chunk={chunk} ratio={ratio} last={last} "
                                                                  f"cap={cap} park={park}")
        np.testing.assert_array_equal(got["t"], ref["t"])
    assert tracing.level_sizes(1000, 2, 64) == [1000, 500, 250, 125, 64]
    assert tracing.level_sizes(50, 2, 64) == [50]
    searching = tracing.search_stages(alg)
    # (the marching and ladder stages search; the refinement and certification are parked)
    assert searching == (alg.search_stages if method in ("hybrid_secant", "march_bisect") else len(tracing._stages(alg)))
    assert searching < len(tracing._stages(alg)) or method in ("sphere_trace", "march_newton")
    assert tracing.search_stages(alg, park=False) == len(tracing._stages(alg))


@pytest.mark.parametrize("method", ["hybrid_secant", "march_secant", "march_newton", "march_bisect"])
def test_steps_read_only_what_they_declare(method):
    """The compacting drivers carry only ``alg.reads(stage)`` into a stage: each step, given only
    those entries, computes what it computes on the whole state (every stage, on rays in it)."""
    from impls.core import rootfind
    from impls.numpy import derivatives

    case = get_case("csg.union.camera.32x32")
    seen = set()
    # ladder steps after 2 marching steps reach the ladder stage; the hybrid's certification stage
    # follows long extrapolated crossings, which the default ladder_after (64) leaves to the march
    for after in ((2, 64) if method == "hybrid_secant" else (2,)):
        knobs = {k.name: k.default for k in METHODS[method].knobs}
        knobs["ladder_after"] = after
        alg = make_root_finder(method, case.scene, 0.0, 10.0, knobs)
        # march, ladder, refine (and, for the certified hybrid, certification)
        assert len(alg.stages) == (4 if method == "hybrid_secant" else 3)
        ev = derivatives.ray_eval(case.scene)
        # (with rays grazing the torus: the hybrid's rays go on in ladder steps only once a step
        # stood uncertified, which rays passing within min_step of a surface do)
        from tests.test_rootfind_marching import _torus_box_camera_and_grazing_rays

        _, o, d = _torus_box_camera_and_grazing_rays()
        # (own copies: init shares one array among entries that start equal, and this loop writes
        # rows in place, as no driver does)
        s = {key: np.array(v, copy=True) for key, v in alg.init(np, o, d, ev).items()}
        for _ in range(40):  # step every stage on its own rays, full state against declared entries
            for k, name in enumerate(alg.stages):
                rows = np.nonzero((s["status"] == rootfind.IN) & (s["phase"] == k))[0]
                if not rows.size:
                    continue
                seen.add(name)
                sub = {key: v[rows] for key, v in s.items()}
                full = getattr(alg, name)(np, sub, o[rows], d[rows], ev)
                lean = getattr(alg, name)(np, {key: sub[key] for key in alg.reads(name)}, o[rows], d[rows], ev)
                for key in lean:
                    np.testing.assert_array_equal(lean[key], full[key], err_msg=f"{name}: {key}")
                assert {"status", "t", "iterations", "evals"} <= set(lean)
                for key, v in full.items():
                    s[key][rows] = v
    assert seen == set(alg.stages)


def test_sphere_trace_stages_read_what_they_declare_and_the_masked_step_matches_them():
    """Sphere tracing's two stages (the tracer; the refinement of a probe's bracket wider than δ,
    SphereTrace.step_refine) read only ``alg.reads(stage)``, and the one step a masked driver runs
    instead (``step_masked``: one φ evaluation for both) gives the staged drivers' per-ray results.
    The unit sphere's 64² camera in float32 at the default tol: the hits at slope 0.25–0.5 probe
    twice (the first probe lands within φ's rounding) and go on to refinement, where those the
    dtype resolves to δ are CONVERGED and the rest UNCERTIFIED."""
    from impls.core import rootfind
    from impls.numpy import derivatives

    case = get_case("sphere.camera.64x64")
    alg = make_root_finder("sphere_trace", case.scene, case.t_min, case.t_max,
                           {k.name: k.default for k in METHODS["sphere_trace"].knobs})
    assert alg.stages == ("step", "step_refine") and alg.masked_stages == ("step_masked",)
    ev = derivatives.ray_eval(case.scene)
    o, d = case.origins.astype(np.float32), case.directions.astype(np.float32)
    s = {key: np.array(v, copy=True) for key, v in alg.init(np, o, d, ev).items()}
    masked = {key: np.array(v, copy=True) for key, v in s.items()}
    refined = np.zeros(len(o), bool)
    for _ in range(alg.max_steps + 1):
        for k, name in enumerate(alg.stages):
            rows = np.nonzero((s["status"] == rootfind.IN) & (s["phase"] == k))[0]
            if not rows.size:
                continue
            refined[rows] |= k == 1
            sub = {key: v[rows] for key, v in s.items()}
            full = getattr(alg, name)(np, sub, o[rows], d[rows], ev)
            lean = getattr(alg, name)(np, {key: sub[key] for key in alg.reads(name)}, o[rows], d[rows], ev)
            for key in lean:
                np.testing.assert_array_equal(lean[key], full[key], err_msg=f"{name}: {key}")
            for key, v in full.items():
                s[key][rows] = v
        live = masked["status"] == rootfind.IN
        if live.any():
            new = alg.step_masked(np, masked, o, d, ev)
            masked = {key: np.where(live, new[key], v) for key, v in masked.items()}
        if not (live.any() or (s["status"] == rootfind.IN).any()):
            break
    staged, one = rootfind.outputs(np, s), rootfind.outputs(np, masked)
    for key in rootfind.STATE_OUT:
        np.testing.assert_array_equal(one[key], staged[key], err_msg=key)
    assert (staged["status"][refined] == rootfind.CONV).sum() > 10 and (staged["status"][refined] == rootfind.UNC).sum() > 10


def test_jax_constant_step_marches_keep_a_larger_smallest_level(monkeypatch):
    """A constant-step march (the march_* methods, whose rays take at most (t_max − t_min)/step
    steps) runs its smallest level at ``last_constant`` rows, the certified methods at ``last``;
    a runner's larger ``last`` (one level for a run that times nothing) wins for both.  The levels
    change no per-ray result (test above, march_newton at last sizes 1 to 40)."""
    pytest.importorskip("jax")
    from impls.jax import driver
    from impls.jax.backend import JaxBackend

    case = get_case("torus.camera.32x32")
    knobs = lambda m: {k.name: k.default for k in METHODS[m].knobs}  # noqa: E731
    march = make_root_finder("march_secant", case.scene, 0.0, 10.0, knobs("march_secant"))
    certified = make_root_finder("hybrid_secant", case.scene, 0.0, 10.0, knobs("hybrid_secant"))
    st = driver.MaskedSettings()
    assert driver.constant_steps(march) and not driver.constant_steps(certified)
    assert driver.smallest_level(march, st) == driver.LAST_CONSTANT > driver.smallest_level(certified, st) == driver.LAST
    one = driver.MaskedSettings(last=st.chunk)
    assert driver.smallest_level(march, one) == driver.smallest_level(certified, one) == st.chunk
    assert driver.MaskedSettings(last_constant=16).record()["last_constant"] == 16

    seen = []
    b = JaxBackend("cpu")
    monkeypatch.setattr(driver, "run_loop", lambda alg, o, d, ev, **kw: seen.append(kw["last"]))
    b.run_loop(march, None, None, None)
    b.run_loop(certified, None, None, None)
    assert seen == [driver.LAST_CONSTANT, driver.LAST]
