"""``bench run`` exits 1 when a stage beside its configurations failed, or a claim's check could not
run, after writing the report: before, a run whose claims ledger raised exited 0 with the section
missing from its report, and a CI job did not see it (``bench claims`` already exited 1 there)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pandas as pd

from bench.commands._common import ProgressLines
from bench.commands._run_stages import closing_summary, stage_errors
from bench.run.results import read_results
from tests.conftest import HANG_GUARD_S

ROOT = Path(__file__).resolve().parent.parent


def _ledger(path: Path, verdicts: dict[str, str]) -> None:
    pd.DataFrame({"id": list(verdicts), "verdict": list(verdicts.values())}).to_csv(path / "claims.csv", index=False)


def test_a_failed_stage_or_an_unchecked_claim_is_an_error_and_a_verdict_is_not(tmp_path):
    assert stage_errors({}, tmp_path) == []  # neither stage asked for (--no-claims --no-stability)
    assert stage_errors({"stability": "ran", "claims": "ran"}, tmp_path) == []  # (no ledger written: none read)
    errors = stage_errors({"stability": "stability stage failed: planted", "claims": "claims failed: boom"}, tmp_path)
    assert errors == ["stability: stability stage failed: planted", "claims: claims failed: boom"]
    _ledger(tmp_path, {"1a": "holds", "9": "fails", "10b": "fails", "2a": "holds under conditions"})
    assert stage_errors({"claims": "ran"}, tmp_path) == []  # "fails" is the ledger's verdict, not an error
    _ledger(tmp_path, {"1a": "holds", "4c": "error", "9": "fails", "7": "error"})
    (err,) = stage_errors({"claims": "ran"}, tmp_path)
    assert "could not run" in err and "4c, 7" in err and "bench claims --only" in err


def test_the_run_exit_code_counts_a_failed_claims_stage(tmp_path, capsys):
    out = tmp_path / "run"
    p = subprocess.run([sys.executable, "-m", "bench", "run", "--case", "sphere.camera.64x64", "--method", "sphere_trace",
                        "--backend", "numpy", "--accuracy-only", "--no-claims", "--no-stability", "--no-progress",
                        "--out", str(out)], cwd=ROOT, capture_output=True, text=True, timeout=HANG_GUARD_S)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    df = read_results(out)
    env = json.loads((out / "environment.json").read_text())
    assert closing_summary(df, env, out, ProgressLines(periodic=False))[0] == 0
    code, errors = closing_summary(df, {**env, "claims": "claims failed: RuntimeError: planted"}, out,
                                   ProgressLines(periodic=False))
    assert code == 1 and errors == ["claims: claims failed: RuntimeError: planted"]
    capsys.readouterr()
