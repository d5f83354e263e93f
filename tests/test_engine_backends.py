"""The engine backends (impls/engine.py: ``embree``, ``open3d``) as plug-ins: declared in pyproject.toml
and installed by CI, registered by entry point, Unavailable with the install command when their
package is missing, and a run on a mesh case puts their float32 rows into "which to pick" and the
stability matrix.  Their answers are checked by the conformance suite (tests/conformance/,
``raycast``)."""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path

import pytest

from impls import METHODS, registry
from tests.conftest import bench_cli

ROOT = Path(__file__).resolve().parents[1]
ENGINES = {"embree": ("impls.embree.backend:EmbreeBackend", "embreex"),
           "open3d": ("impls.open3d.backend:Open3DBackend", "open3d")}


def _importable(module: str) -> bool:
    try:
        __import__(module)
    except Exception:  # open3d without its Debian library raises OSError
        return False
    return True


def _fake_entry_points(tmp_path: Path) -> Path:
    """The entry points pyproject.toml declares, as ``pip install -e .`` would publish them, in a fake
    dist-info (installing would repoint the shared environment)."""
    dist = tmp_path / "isobench_engines_probe-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: isobench-engines-probe\nVersion: 0.1\n")
    lines = "\n".join(f"{name} = {spec}" for name, (spec, _) in ENGINES.items())
    (dist / "entry_points.txt").write_text(f"[{registry.ENTRY_POINT_GROUP}]\n{lines}\n")
    return tmp_path


def test_pyproject_declares_entry_points_extra_and_pins_and_ci_installs_it():
    import tomllib

    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    for name, (spec, _) in ENGINES.items():
        assert meta["entry-points"][registry.ENTRY_POINT_GROUP][name] == spec
    extra = meta["optional-dependencies"]["engines"]
    assert any(r.startswith("embreex") for r in extra) and any(r.startswith("open3d") for r in extra)
    pins = (ROOT / "constraints.txt").read_text().split()
    assert "embreex==4.4.0.post1" in pins and "open3d==0.20.0" in pins
    # not in `all` (the README's install), so CI installs it, with open3d's Debian library, before
    # the README's test command
    assert not any("engines" in e for e in meta["optional-dependencies"]["all"])
    ci = (ROOT / ".ci" / "run").read_text()
    assert ci.index('-e ".[engines]"') < ci.index("python -m pytest") and "libusb-1.0-0" in ci


@pytest.mark.parametrize("name", sorted(ENGINES))
def test_plugs_in_by_entry_point(tmp_path, monkeypatch, name):
    spec, module = ENGINES[name]
    if not _importable(module):
        pytest.skip(f"{module} is not importable here (pip install -e '.[engines]')")
    monkeypatch.syspath_prepend(str(_fake_entry_points(tmp_path)))
    assert name in registry.default_ids()
    b = registry.resolve(name)
    assert b.id == name and b.methods() == ("raycast",) and b.capabilities.dtypes == ("float32",)
    assert METHODS["raycast"].dtypes == ("float32",)


@pytest.mark.parametrize("name", sorted(ENGINES))
def test_without_the_package_it_is_unavailable_with_the_install_command(tmp_path, monkeypatch, name):
    from bench.run.configuration import Config, skip_reason
    from reference.cases import get_case

    spec, module = ENGINES[name]
    monkeypatch.syspath_prepend(str(_fake_entry_points(tmp_path)))
    monkeypatch.setitem(sys.modules, module, None)  # not installed
    if module == "embreex":
        for sub in ("embreex.rtcore_scene", "embreex.mesh_construction"):
            monkeypatch.setitem(sys.modules, sub, None)
    monkeypatch.delitem(sys.modules, spec.partition(":")[0], raising=False)
    gone = registry.resolve(name)
    assert isinstance(gone, registry.Unavailable) and not gone.unknown
    assert "pip install -c constraints.txt -e '.[engines]'" in gone.reason
    if importlib.util.find_spec("trimesh") and importlib.util.find_spec("igl"):
        cfg = Config(get_case("mesh.fin.thin"), name, "raycast", "float32", {})
        assert "backend unavailable" in skip_reason(cfg, gone) and ".[engines]" in skip_reason(cfg, gone)


@pytest.mark.slow  # a second process running a bench command
def test_a_mesh_run_picks_an_engine_at_1e_4_and_a_float64_method_at_1e_12(tmp_path):
    """``bench run --backend numpy,embree,open3d --case …``: the engines' rows are float32 raycast
    rows, "which to pick" names an engine at ≤ 1e-4 on the mesh camera and a float64 root finder at
    ≤ 1e-12, and the stability matrix judges the engines in float32."""
    if not all(_importable(m) for _, m in ENGINES.values()):
        pytest.skip("embreex and open3d are not both importable here (pip install -e '.[engines]')")
    pytest.importorskip("igl")
    from bench.run.results import read_results
    from bench.report.summary import which_to_pick

    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(_fake_entry_points(tmp_path)), str(ROOT),
                                                        os.environ.get("PYTHONPATH", "")]))
    out = tmp_path / "run"
    p = bench_cli("run", "--out", out, "--backend", "numpy,embree,open3d", "--case",
                  "mesh.torus.camera.16x16,mesh.fin.grazing.1e-6", "--method", "hybrid_secant,raycast",
                  "--no-claims", "--min-time", "0.01", "--min-repeats", "3", "--no-progress", env=env)
    assert p.returncode == 0, p.stdout + p.stderr
    df = read_results(out)
    eng = df[df["backend"].isin(["embree", "open3d"]) & (df["outcome"] == "ok")]
    assert set(eng["method"]) == {"raycast"} and set(eng["dtype"]) == {"float32"} and len(eng) == 4
    picks = which_to_pick(df).set_index(["case", "target"])["pick"]
    assert picks[("mesh.torus.camera.16x16", 1e-4)].startswith("raycast · ")
    assert picks[("mesh.torus.camera.16x16", 1e-12)] == "hybrid_secant · numpy · float64"
    # the grazing case is an adversarial family's: the stability matrix judges the engines there, in float32
    for name in ("embree", "open3d"):
        assert f"{name} (float32): 1/1 families survived" in p.stdout, p.stdout[-3000:]
    assert "Stability" in (out / "report.html").read_text()
