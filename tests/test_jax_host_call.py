"""A host (numpy) function inside a jax program as a named custom call (reference.jax_host_call):
the same values as the function, under jit, vmap and both float dtypes; a Python error in the
function is the program's error, with its message; and the programs calling it — the mesh cases'
kernels — are kept by jax's persistent compilation cache, which never keeps a program with a
``jax.pure_callback`` (every run compiled them afresh)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import bench_cli

jax = pytest.importorskip("jax")
jnp = pytest.importorskip("jax.numpy")

import impls.jax.backend  # noqa: E402,F401 - float64 on (jax_enable_x64), as every isobench jax caller has it
from reference.jax_host_call import host_call, on_cpu  # noqa: E402

pytestmark = pytest.mark.skipif(not on_cpu(), reason="the custom call runs where jax's default backend is the CPU")


def _norms(x):
    return (np.sqrt(np.sum(x * x, axis=-1)) - 1.0, 2.0 * x)


def _phi(x):
    return host_call("isobench_test_norms", _norms, x, (jax.ShapeDtypeStruct(x.shape[:-1], x.dtype),
                                                          jax.ShapeDtypeStruct(x.shape, x.dtype)))


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_host_call_returns_the_functions_values_under_jit_and_vmap(dtype):
    x = np.random.default_rng(1).normal(size=(7, 5, 3)).astype(dtype)
    want = _norms(x.astype(np.float64))
    got = jax.jit(_phi)(jnp.asarray(x))
    assert [g.dtype for g in got] == [np.dtype(dtype)] * 2
    for g, w in zip(got, want):
        np.testing.assert_allclose(np.asarray(g), w, rtol=1e-6 if dtype == "float32" else 0, atol=0)
    batched = jax.jit(jax.vmap(_phi))(jnp.asarray(x))
    for g, w in zip(batched, got):
        assert np.array_equal(np.asarray(g), np.asarray(w))
    # inside a loop (how the root finders call φ): one call per iteration, fresh points each time
    total = jax.jit(lambda a: jax.lax.fori_loop(0, 3, lambda i, s: s + _phi(a + i)[0], jnp.zeros(a.shape[:-1], a.dtype)))
    expect = sum(_norms(x.astype(np.float64) + i)[0] for i in range(3))
    np.testing.assert_allclose(np.asarray(total(jnp.asarray(x))), expect, rtol=1e-5 if dtype == "float32" else 1e-15)


def test_off_the_cpu_it_is_a_pure_callback_with_the_same_values(monkeypatch):
    """Where jax's default backend is not the CPU (a GPU machine) a CPU custom call cannot run in
    the program: the same function goes through ``jax.pure_callback`` (forced here on the CPU)."""
    import reference.jax_host_call as hc

    monkeypatch.setattr(hc, "on_cpu", lambda: False)
    x = jnp.asarray(np.random.default_rng(2).normal(size=(6, 3)))
    lowered = jax.jit(_phi).lower(x)
    assert "isobench_test_norms" not in lowered.as_text()
    got = lowered.compile()(x)
    for g, w in zip(got, _norms(np.asarray(x))):
        np.testing.assert_allclose(np.asarray(g), w, rtol=0, atol=0)


def test_an_error_in_the_host_function_is_the_programs_error():
    def broken(x):
        raise ValueError("no closest point for this query")

    f = jax.jit(lambda x: host_call("isobench_test_broken", broken, x, (jax.ShapeDtypeStruct(x.shape[:-1], x.dtype),))[0])
    with pytest.raises(Exception, match="isobench_test_broken: ValueError: no closest point for this query"):
        jax.block_until_ready(f(jnp.ones((4, 3))))


def test_a_wrong_result_shape_is_an_error_not_garbage():
    f = jax.jit(lambda x: host_call("isobench_test_short", lambda p: (np.zeros(2),), x,
                                    (jax.ShapeDtypeStruct(x.shape[:-1], x.dtype),))[0])
    with pytest.raises(Exception, match="isobench_test_short"):
        jax.block_until_ready(f(jnp.ones((4, 3))))


def test_a_program_calling_the_host_is_not_a_pure_callback():
    """What keeps it cacheable: jax writes no program with host callbacks to its persistent cache."""
    lowered = jax.jit(_phi).lower(jnp.ones((4, 3)))
    assert "isobench_test_norms" in lowered.as_text()
    assert not lowered._lowering.compile_args.get("host_callbacks")


@pytest.mark.slow  # two runs that compile and load jax kernels
def test_a_second_run_reuses_the_mesh_kernels_from_the_cache(tmp_path):
    cache = tmp_path / "cache"
    args = ["--case", "mesh.torus.camera.16x16", "--method", "sphere_trace,hybrid_secant", "--backend", "jax:cpu",
            "--accuracy-only", "--no-claims", "--no-stability", "--no-progress", "--cache-dir", cache]
    from bench.run.results import read_results

    rows = {}
    for name in ("cold", "warm"):
        p = bench_cli("run", "--out", tmp_path / name, *args)
        assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
        df = read_results(tmp_path / name)
        rows[name] = df[df["outcome"] == "ok"].sort_values(["method", "knob", "quantity"]).reset_index(drop=True)
    assert len(rows["cold"]) and "compiled" in set(rows["cold"]["compile_cache"])
    assert set(rows["warm"]["compile_cache"]) == {"reused"}, rows["warm"][["method", "knob", "compile_cache"]]
    same = ["method", "knob", "quantity", "status_counts", "error_max", "n_false_hit", "n_false_miss", "evals_per_ray"]
    assert rows["cold"][same].equals(rows["warm"][same])
