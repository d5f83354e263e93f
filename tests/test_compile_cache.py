"""Compiled kernels are kept between runs in one cache directory (``--cache-dir``, default
``$XDG_CACHE_HOME/isobench``; ``--no-cache`` for a cold start): each row says whether its kernel
was compiled or reused, and reusing changes no result."""

from __future__ import annotations

import json

import pytest

from bench.run.environment import default_cache_dir
from bench.run.results import read_results
from tests.conftest import bench_cli

#: what must be identical whether a kernel was compiled or came from the cache
SAME = ["case_id", "backend", "method", "knob", "quantity", "outcome", "status_counts", "error_max", "error_p99",
        "n_false_hit", "n_false_miss", "evals_per_ray", "iterations_max"]


def test_default_cache_dir_follows_xdg(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert default_cache_dir() == tmp_path / "isobench"
    monkeypatch.delenv("XDG_CACHE_HOME")
    assert default_cache_dir().parts[-2:] == (".cache", "isobench")


@pytest.mark.slow  # three runs that compile jax and numba kernels
def test_a_second_run_reuses_every_kernel_and_no_cache_compiles_afresh(tmp_path):
    cache = tmp_path / "cache"
    args = ["--case", "torus.camera.32x32", "--method", "hybrid_secant,sphere_trace", "--accuracy-only", "--no-claims",
            "--no-progress"]
    from impls import registry

    backends = [b for b in ("jax:cpu", "numba") if not isinstance(registry.resolve(b), registry.Unavailable)]
    if not backends:
        pytest.skip("neither jax nor numba is installed")
    args += ["--backend", ",".join(backends)]
    runs = {}
    for name, extra in (("cold", ["--cache-dir", cache]), ("warm", ["--cache-dir", cache]), ("none", ["--no-cache"])):
        p = bench_cli("run", "--out", tmp_path / name, *extra, *args)
        assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
        runs[name] = read_results(tmp_path / name).sort_values(SAME[:5]).reset_index(drop=True)
        env = json.loads((tmp_path / name / "environment.json").read_text())
        assert env["cache_dir"] == (str(cache.resolve()) if name != "none" else "none (--no-cache)")
    ok = {k: df[df["outcome"] == "ok"] for k, df in runs.items()}
    assert len(ok["cold"]) and set(ok["cold"]["backend"]) == set(backends)
    # cold: each backend compiles (numba once per scene structure and kernel, reused by the other
    # knob settings and by the other method sharing the kernel: the certified methods evaluate φ
    # with one kernel; jax once per method and structure, the knob settings sharing it: knobs traced)
    cold = ok["cold"].groupby(["backend"])["compile_cache"].agg(set)
    assert all("compiled" in v and v <= {"compiled", "reused"} for v in cold), cold
    if "jax:cpu" in backends:
        jax_cold = ok["cold"][ok["cold"]["backend"] == "jax:cpu"].drop_duplicates(["method", "knob"])
        per_method = jax_cold.groupby("method")["compile_cache"].agg(list)
        # each method compiles; its settings that differ only in traced knobs (the tolerance
        # sweeps) reuse a kernel compiled for another setting
        assert all("compiled" in v and "reused" in v for v in per_method), per_method
    assert set(ok["warm"]["compile_cache"]) == {"reused"}, ok["warm"][["backend", "method", "compile_cache"]]
    # --no-cache: nothing from disk; numba compiles (and reuses within the run); jax states only
    # the reuse of a kernel this run compiled (whether a fresh compile hit a cache it cannot say)
    none = ok["none"]
    assert set(none.loc[none["backend"] == "jax:cpu", "compile_cache"].dropna()) <= {"reused"}
    assert "compiled" in set(none.loc[none["backend"] == "numba", "compile_cache"]) or "numba" not in backends
    for name in ("warm", "none"):
        a, b = runs["cold"][SAME], runs[name][SAME]
        assert a.equals(b), (name, a.compare(b))
    assert (cache / "jax").is_dir() or "jax:cpu" not in backends
    assert any((cache / "numba").glob("*.py")) or "numba" not in backends
