"""``--resume`` checks what it resumes (issue 33): a case whose content changed since the run
started is refused, naming it, unless ``--rerun-case`` (finding 3); the claims and stability
choices are restored with the rest of the plan (finding 8).

An interrupted run is made deterministically: a finished run whose rows are cut to the first
half and whose environment.json says ``complete: "false"`` — what a kill leaves (the kill itself
is tested in ``tests/test_bench_resume.py``)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pandas as pd
import pytest

from bench.run.results import read_results
from tests.conftest import HANG_GUARD_S

ROOT = Path(__file__).resolve().parent.parent

CASE_MODULE = textwrap.dedent('''
    import os

    import numpy as np

    from reference import CallableField, Case, rays


    def ball(x, xp):
        return xp.sqrt(xp.sum(x * x, axis=-1)) - 1.0


    o, d = rays.pinhole(eye=(0, 0, 3), look_at=(0, 0, 0), up=(0, 1, 0), fov_deg=40, width=4, height=4)
    # an unseeded factory, made reproducible for the test: the rays move with CHCASE_SHIFT
    o = o + np.array([float(os.environ.get("CHCASE_SHIFT", "0")), 0.0, 0.0])
    CASES = [Case(id="user.changing.camera", scene=CallableField(ball, lipschitz=1.0, name="chcase.ball"),
                  origins=o, directions=d, t_min=0.0, t_max=6.0)]
''')
RUN = ["--cases", "chcase:CASES", "--case", "user.*,sphere.camera.64x64", "--backend", "numpy", "--method",
       "sphere_trace,march_bisect", "--accuracy-only", "--no-claims", "--no-progress"]


def bench(tmp_path, *args, shift="0"):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), str(ROOT)]), CHCASE_SHIFT=shift)
    return subprocess.run([sys.executable, "-m", "bench", *args], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=HANG_GUARD_S)


def interrupt(out: Path) -> int:
    """Cut the run in ``out`` to half its rows (every case keeps some) and mark it incomplete."""
    df = read_results(out)
    g = df.groupby("case_id")
    keep = df[g.cumcount() < g["case_id"].transform(lambda c: max(1, len(c) // 2))]
    (out / "results.parquet").unlink()
    keep.to_csv(out / "results.csv", index=False)
    env = json.loads((out / "environment.json").read_text())
    env.update(complete="false", incomplete_reason="killed (planted)")
    (out / "environment.json").write_text(json.dumps(env))
    return len(keep)


@pytest.fixture
def interrupted(tmp_path):
    (tmp_path / "chcase.py").write_text(CASE_MODULE)
    out = tmp_path / "run"
    p = bench(tmp_path, "run", "--out", str(out), *RUN)
    assert p.returncode == 0, p.stdout + p.stderr
    full = read_results(out)
    interrupt(out)
    return out, full


def test_resume_refuses_a_case_that_changed_naming_it(tmp_path, interrupted):
    """Finding 3: the resume finished with rows of two versions of one case, complete, exit 0."""
    out, full = interrupted
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    p = bench(tmp_path, "run", "--resume", "--out", str(out), shift="1e-3")
    assert p.returncode == 2, p.stdout + p.stderr
    assert "Traceback" not in p.stderr
    err = [ln for ln in p.stderr.splitlines() if "error:" in ln]
    assert len(err) == 1 and "user.changing.camera" in err[0] and "--rerun-case" in err[0], p.stderr
    assert "sphere.camera.64x64" not in err[0]  # the unchanged case is not blamed
    after = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    assert {k: v for k, v in after.items() if k != ".isobench.lock"} == \
        {k: v for k, v in before.items() if k != ".isobench.lock"}  # refused before any write


def test_rerun_case_runs_the_changed_case_again_whole(tmp_path, interrupted):
    out, full = interrupted
    kept = read_results(out)
    p = bench(tmp_path, "run", "--resume", "--out", str(out), "--rerun-case", "user.*", shift="1e-3")
    assert p.returncode == 0, p.stdout + p.stderr
    df = read_results(out)
    versions = df.groupby("case_id")["case_version"].agg(lambda v: set(map(str, v)))
    assert all(len(v) == 1 for v in versions), versions
    changed = full.loc[full["case_id"] == "user.changing.camera", "case_version"].iloc[0]
    assert versions["user.changing.camera"] != {str(changed)}
    assert len(df) == len(full) and not df.duplicated(["case_id", "backend", "dtype", "method", "knob",
                                                       "quantity"]).any()
    # the unchanged case's rows were kept, not re-measured
    same = kept[kept["case_id"] == "sphere.camera.64x64"]
    merged = same.merge(df, on=["case_id", "method", "knob", "quantity"], suffixes=("_a", "_b"))
    assert len(merged) == len(same) and (merged["error_max_a"] == merged["error_max_b"]).all()
    assert json.loads((out / "environment.json").read_text())["complete"] == "true"


def test_an_unchanged_resume_still_passes(tmp_path, interrupted):
    out, full = interrupted
    p = bench(tmp_path, "run", "--resume", "--out", str(out))
    assert p.returncode == 0, p.stdout + p.stderr
    assert len(read_results(out)) == len(full)


def test_resume_restores_the_claims_and_stability_choice(tmp_path):
    """Finding 8: --resume re-ran the claims stage unless --no-claims was given again."""
    (tmp_path / "chcase.py").write_text(CASE_MODULE)
    out = tmp_path / "run"
    p = bench(tmp_path, "run", "--out", str(out), *RUN)
    assert p.returncode == 0, p.stdout + p.stderr
    recorded = json.loads(json.loads((out / "environment.json").read_text())["run_options"])
    assert recorded["no_claims"] is True
    interrupt(out)
    p = bench(tmp_path, "run", "--resume", "--out", str(out))
    assert p.returncode == 0, p.stdout + p.stderr
    assert "claims:" not in p.stdout and not (out / "claims.csv").exists(), p.stdout
    assert json.loads((out / "environment.json").read_text()).get("claims") is None
