"""Marching cubes as a method family (bench.studies.extraction) and its float64 scoring against the exact
surface (reference.surface_distance)."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from bench.studies.extraction import (applies, extract, hausdorff_rates, markdown_section, plot, run_extraction, summary_table)
from reference.cases import Case, get_case
from reference.mesh import MeshSDF
from reference.primitives import Box, Sphere
from reference.surface_distance import distance_to_surface, mesh_samples, mesh_to_surface_errors, surface_samples


def _case(case_id, scene):
    return Case(id=case_id, scene=scene, origins=np.zeros((1, 3)), directions=np.array([[0.0, 0.0, 1.0]]))


class _Broken(Sphere):
    """A sphere whose φ raises (a user field with a bug)."""

    def _eval(self, x, xp, cursor):
        raise RuntimeError("planted failure in φ")


def test_sphere_distance_is_the_analytic_one():
    """|φ| at the vertices and face samples of an extracted unit sphere is | |x| − 1 |."""
    out = extract(Sphere(), 24)
    assert out["faces"].shape[0] > 100
    pts, _, _ = mesh_samples(out["vertices"], out["faces"], 3)
    d, err = distance_to_surface(Sphere(), pts)
    analytic = np.abs(np.linalg.norm(pts, axis=1) - 1.0)
    np.testing.assert_allclose(d, analytic, rtol=0, atol=4e-16)
    assert np.all(err < 1e-14)
    m = mesh_to_surface_errors(Sphere(), out["vertices"], out["faces"], 0.05)
    assert m["hausdorff_mesh_to_surface"] == pytest.approx(analytic.max(), abs=4e-16)
    # vertices lie on cell edges by linear interpolation: within the mesh samples' max
    v_err = np.abs(np.linalg.norm(out["vertices"], axis=1) - 1.0).max()
    assert 0 < v_err <= m["hausdorff_mesh_to_surface"]


def test_sphere_hausdorff_is_second_order():
    """H(h) ~ C h² for the unit sphere: the fitted slope of log H vs log h is 2 ± 0.2, and H
    falls at every refinement."""
    hs, es, cs = [], [], []
    for n in (16, 32, 64, 128):
        out = extract(Sphere(), n)
        h = float(out["spacing"][0])
        m = mesh_to_surface_errors(Sphere(), out["vertices"], out["faces"], 0.5 * h)
        assert m["covering_surface"] <= 0.5 * h and m["surface_cover_certified"]
        hs.append(h)
        es.append(m["hausdorff"])
        cs.append(m["chamfer"])
    assert all(b < a for a, b in zip(es, es[1:])) and all(b < a for a, b in zip(cs, cs[1:]))
    slope = np.polyfit(np.log(hs), np.log(es), 1)[0]
    assert 1.8 <= slope <= 2.2, (hs, es, slope)
    assert es[-1] < 1e-3


def test_shifted_box_mesh_hausdorff_equals_the_shift():
    """The box mesh moved by δ along x is at Hausdorff distance exactly δ from the box (its
    ±x faces and corners are δ away, nothing farther), on both sides."""
    import trimesh

    half = np.array([0.5, 0.4, 0.3])
    tm = trimesh.creation.box(extents=2 * half)
    for delta in (1e-2, 1e-5):
        V = np.asarray(tm.vertices, np.float64) + [delta, 0.0, 0.0]
        m = mesh_to_surface_errors(Box(tuple(half)), V, np.asarray(tm.faces), 0.02)
        assert m["hausdorff_mesh_to_surface"] == pytest.approx(delta, rel=1e-9, abs=1e-15)
        assert m["hausdorff_surface_to_mesh"] == pytest.approx(delta, rel=1e-9, abs=1e-15)
        assert m["hausdorff"] == pytest.approx(delta, rel=1e-9, abs=1e-15)
        # the ±x faces (area fraction 2·0.8·0.6/4.72 ≈ 0.2) are δ away; the rest 0 to δ
        frac = 2 * (4 * half[1] * half[2]) / (2 * 4 * (half[0] * half[1] + half[1] * half[2] + half[0] * half[2]))
        assert frac * delta * 0.99 <= m["chamfer_mesh_to_surface"] <= delta


def test_mesh_scene_against_itself_and_extracted():
    """MeshSDF (torus.npz): its own triangles are at distance 0 (to rounding); marching cubes of
    its φ converges (H falls with N, and is below the tube radius 0.25)."""
    mesh = MeshSDF.load("torus")
    s = surface_samples(mesh, 0.05)
    assert s.certified_cover and s.covering_radius <= 0.05
    m = mesh_to_surface_errors(mesh, mesh.vertices, mesh.faces, 0.05, surface=s)
    assert m["hausdorff"] <= 1e-12 and m["distance_method"] == "mesh"
    rows = run_extraction([_case("mesh.torus.test", mesh)], resolutions=(16, 32), repeats=1)
    df = pd.DataFrame(rows)
    assert set(df["outcome"]) == {"ok"} and len(df) == 4
    h = df[df["quantity"] == "hausdorff"].sort_values("resolution")
    e = h["error_max"].to_numpy()
    assert np.all(np.isfinite(e)) and e[1] < e[0] < 0.25
    assert np.all(h["n_faces"] > 0) and np.all(h["n_vertices"] > 0)
    assert np.all(h["reference_error_bound"] < 1e-12)


def test_skipped_and_failed_rows_and_the_rest_run(tmp_path):
    """No bounding sphere → skipped rows with the reason; a φ that raises → failed rows with the
    traceback; the sphere after both still runs."""
    plane = get_case("plane.camera.32x32")
    broken = _case("broken.sphere", _Broken())
    sphere = _case("sphere.test", Sphere())
    assert "bounding sphere" in applies(plane.scene)
    rows = run_extraction([plane, broken, sphere], resolutions=(12, 20), repeats=2)
    df = pd.DataFrame(rows)
    sk = df[df["case_id"] == plane.id]
    assert len(sk) == 2 and set(sk["outcome"]) == {"skipped"} and all("bounding sphere" in r for r in sk["reason"])
    fl = df[df["case_id"] == "broken.sphere"]
    assert set(fl["outcome"]) == {"failed"} and len(fl) == 4
    assert all("planted failure" in r for r in fl["reason"]) and all("Traceback" in t for t in fl["traceback"])
    ok = df[df["case_id"] == "sphere.test"]
    assert set(ok["outcome"]) == {"ok"} and len(ok) == 4
    assert set(ok["quantity"]) == {"hausdorff", "chamfer"} and set(ok["knob"]) == {"resolution=12", "resolution=20"}
    assert set(ok["family"]) == {"extract"} and set(ok["method"]) == {"marching_cubes"}
    assert all(ok["n_samples"] == 2) and np.all(ok["time_median_s"] > 0)
    ham = ok[ok["quantity"] == "hausdorff"]
    assert np.all(ham["error_max"] == ham["hausdorff"]) and np.all(ham["error_max"] >= ham["chamfer"])
    # report pieces
    md = markdown_section(df, image="extraction.png")
    assert "sphere.test" in md and "broken.sphere: failed" in md and "plane.camera.32x32: skipped" in md
    assert plot(df, tmp_path / "extraction.png").stat().st_size > 1000
    assert len(summary_table(df)) == 5  # plane once, broken and sphere per resolution
    assert hausdorff_rates(df).set_index("case").loc["sphere.test", "slope"] > 1


def test_lipschitz_fallback_brackets_the_distance():
    """|x|² − 1 (not an SDF, L = 13): the certified upper bound equals the true distance
    | |x| − 1 | to bisection accuracy, and its stated error bound covers the gap to |φ|/L."""
    from reference.implicits import AlgebraicSphere

    scene = AlgebraicSphere(domain_radius=6.5)
    rng = np.random.default_rng(0)
    x = rng.normal(size=(200, 3))
    x *= (rng.uniform(0.7, 1.3, 200) / np.linalg.norm(x, axis=1))[:, None]
    d, err = distance_to_surface(scene, x)
    true = np.abs(np.linalg.norm(x, axis=1) - 1.0)
    assert np.all(d >= true - 1e-12) and np.all(d - true <= 1e-9)
    assert np.all(d - err <= true + 1e-12)


def test_bad_input():
    with pytest.raises(ValueError, match="bounds=\\(lo, hi\\)"):
        extract(get_case("plane.camera.32x32").scene, 16)
    with pytest.raises(ValueError, match="resolution must be an integer ≥ 4"):
        extract(Sphere(), 3)
    with pytest.raises(ValueError, match="repeats"):
        run_extraction([], repeats=0)
    out = extract(get_case("plane.camera.32x32").scene, 8, bounds=((-1, -1, -1), (1, 1, 1)))
    assert out["faces"].shape[0] > 0 and np.allclose(out["vertices"][:, 2], 0.0, atol=1e-12)


def test_extract_command_writes_results_section_and_plot(tmp_path):
    """``python -m bench extract``: rows, the report section and the plot, atomically, in --out;
    an --out that already holds files is refused (nothing is overwritten)."""
    from bench.commands import main
    from bench.run.results import read_results

    out = tmp_path / "ex"
    assert main(["extract", "--case", "sphere.grazing.1e-6", "--resolution", "8", "--resolution", "16",
                 "--repeats", "1", "--out", str(out)]) == 0
    df = read_results(out)
    assert set(df["quantity"]) == {"hausdorff", "chamfer"} and set(df["knob"]) == {"resolution=8", "resolution=16"}
    assert (out / "extraction.md").read_text().startswith("## Surface extraction")
    assert (out / "extraction.png").stat().st_size > 0
    assert main(["extract", "--case", "sphere.grazing.1e-6", "--out", str(out)]) == 2
