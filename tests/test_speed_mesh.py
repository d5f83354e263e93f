"""``bench speed --mesh`` (bench/speed_mesh.py) on 8² rays: every backend answers every mesh camera,
an engine in float32 (raycast), a root finder in float64, each scored against the exact hits."""

from __future__ import annotations

import json

import pytest

pytest.importorskip("trimesh")
pytest.importorskip("igl")

from tests.conftest import bench_cli  # noqa: E402


def test_speed_mesh_rows(tmp_path):
    from impls import registry

    # by its entry point when isobench is installed, else by its module (a checkout on PYTHONPATH)
    engine = next((e for e in ("embree", "impls.embree.backend:EmbreeBackend")
                   if not isinstance(registry.resolve(e), registry.Unavailable)), None)
    ids = "numpy" + (f",{engine}" if engine else "")
    out = tmp_path / "rows.json"
    p = bench_cli("speed", "--mesh", "--side", "8", "--repeats", "1", "--backend", ids, "--no-peers", "--out", out)
    assert p.returncode == 0, p.stdout + p.stderr
    rows = json.loads(out.read_text())
    assert {r["scene"] for r in rows} == {"mesh.torus.camera.8x8", "mesh.fin.camera.8x8", "mesh.blob.camera.8x8"}
    for r in rows:
        assert r["error"] == "" and r["x_unit"] > 0 and r["false_hits"] == 0 and r["false_misses"] == 0, r
        assert json.loads(r["versions"])["numpy"]
    num = [r for r in rows if r["backend"] == "numpy"]
    assert all(r["method"] == "hybrid_secant" and r["dtype"] == "float64" and r["err_max"] <= 1e-9 for r in num)
    if engine:
        eng = [r for r in rows if r["backend"] == engine]
        assert len(eng) == 3
        assert all(r["method"] == "raycast" and r["dtype"] == "float32" and r["err_max"] <= 1e-4 for r in eng)
        assert "embreex" in p.stdout  # the versions line


def test_speed_mesh_refuses_what_it_cannot_do(tmp_path):
    p = bench_cli("speed", "--mesh", "--volume", "--side", "4")
    assert p.returncode == 2 and "--mesh and --volume" in p.stderr
    p = bench_cli("speed", "--mesh", "--side", "4", "--backend", "nosuchbackend")
    assert p.returncode == 2 and "--backend" in p.stderr
