"""``bench edges`` (bench/studies/edges.py) on a small configuration: the rays pass the features where
they should, the float64 engines are never wrong where the float32 ones are, the table and the
plot come out, bad options are refused, and a run directory's report gains the section."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("trimesh")
pytest.importorskip("igl")

from bench.studies import edges  # noqa: E402
from tests.conftest import bench_cli  # noqa: E402


@pytest.fixture(scope="module")
def fin():
    from reference.mesh_cases import stored_mesh

    return stored_mesh("fin")


@pytest.mark.parametrize("family", edges.FAMILIES)
def test_feature_rays_pass_at_the_offset(fin, family):
    """Every ray passes its feature point at distance offset·size from the surface (φ there), on
    the stated side (even rays outside, odd inside), starts outside the mesh, and has a unit
    direction; the features do not depend on the offset."""
    o1, d1 = edges.feature_rays(fin, family, 16, 1e-3, seed=5)
    o2, d2 = edges.feature_rays(fin, family, 16, 1e-4, seed=5)
    np.testing.assert_allclose(np.linalg.norm(d1, axis=1), 1.0, atol=1e-12)
    np.testing.assert_array_equal(d1, d2)
    assert np.all(fin.value(o1, np) > 0)
    x = o1 + 2.0 * fin.bounding_sphere()[1] * d1  # the point the ray passes
    phi = fin.value(x, np)
    side = np.where(np.arange(16) % 2 == 0, 1.0, -1.0)
    assert np.all(np.sign(phi) == side), phi
    assert np.all(np.abs(phi) <= 1e-3 * fin.size * (1 + 1e-6))


def test_trimesh_float64_agrees_with_the_reference_and_engines_break_first(fin):
    pytest.importorskip("embreex")
    from impls import registry

    # by its entry point when isobench is installed, else by its module (a checkout on PYTHONPATH)
    eid = "embree" if not getattr(registry.resolve("embree"), "unknown", False) else "impls.embree.backend:EmbreeBackend"
    engines, notes = edges.engine_callables(["trimesh", eid])
    if "embree" not in engines:
        pytest.skip(f"embree backend unavailable: {notes}")
    df = edges.edges_table(engines, meshes=("fin",), families=("edge",), offsets=(1e-2, 1e-9), n_rays=16, seed=3)
    assert set(df["engine"]) == {"trimesh", "embree"} and (df["error"] == "").all()
    tm = df[df["engine"] == "trimesh"]
    assert (tm["false_hits"] + tm["false_misses"] + tm["wrong_depth"]).sum() == 0
    assert (tm["depth_err_max"] <= 1e-12).all()
    em = df[df["engine"] == "embree"].set_index("offset")
    # at 1e-2 × size float32 resolves the edge; at 1e-9 × size the ray's own float32 rounding
    # (~6e-8 relative) is larger than its offset, and some rays land on the wrong side
    assert em.loc[1e-2, ["false_hits", "false_misses", "wrong_depth"]].sum() == 0
    assert em.loc[1e-9, ["false_hits", "false_misses", "wrong_depth"]].sum() > 0
    fw = edges.first_wrong(df).set_index("engine")
    assert fw.loc["embree", "first_wrong_offset"] == 1e-9 and np.isnan(fw.loc["trimesh", "first_wrong_offset"])
    table = edges.markdown(df)
    assert "δ = 1e-09" in table and "none down to 1e-09" in table


def test_an_engine_that_raises_is_a_row_not_the_end(fin):
    def broken(mesh, o, d):
        raise RuntimeError("planted")

    df = edges.edges_table({"broken": (broken, "float32"), "trimesh": (edges.trimesh_first_hits, "float64")},
                           meshes=("fin",), families=("vertex",), offsets=(1e-3,), n_rays=4)
    assert "planted" in df.set_index("engine").loc["broken", "error"]
    assert "failed on 1 set(s)" in edges.markdown(df)


def test_bench_edges_writes_table_plot_and_report_section(tmp_path):
    run = tmp_path / "run"
    p = bench_cli("run", "--out", run, "--backend", "numpy", "--case", "mesh.fin.thin", "--method", "raycast",
                  "--no-claims", "--no-stability", "--accuracy-only", "--no-progress")
    assert p.returncode in (0, 1), p.stdout + p.stderr  # raycast on numpy: skipped rows only
    p = bench_cli("edges", "--engines", "trimesh", "--mesh", "fin", "--family", "parallel", "--offsets", "1e-3,1e-8",
                  "--rays", "4", "--out", run)
    assert p.returncode == 0, p.stdout + p.stderr
    assert "| trimesh" in p.stdout and "none down to 1e-08" in p.stdout
    assert (run / edges.FILE).is_file() and (run / edges.PLOT).read_bytes()[:4] == b"\x89PNG"
    html = (run / "report.html").read_text()
    assert "Engines at the edge" in html and "data:image/png;base64" in html
    assert "Engines at the edge" in (run / "report.md").read_text()


@pytest.mark.parametrize("args, names", [
    (["--mesh", "nosuch"], "--mesh"), (["--offsets", "1e-3,2"], "--offsets"), (["--offsets", "x"], "--offsets"),
    (["--family", "corner"], "--family"), (["--mesh", ""], "--mesh"), (["--engines", "nosuchbackend"], "--engines"),
    (["--engines", "embree", "--backend", "nosuchbackend"], "--backend"),
])
def test_bench_edges_refuses_bad_options(tmp_path, args, names):
    p = bench_cli("edges", *args, "--rays", "2", "--out", tmp_path / "o")
    assert p.returncode == 2 and names in p.stderr, p.stderr
    assert not (tmp_path / "o").exists()
