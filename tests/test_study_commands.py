"""The study commands (``sampling``, ``extract``) are not silent for minutes and refuse bad
arguments with one ``error:`` line (issue 33, findings 5 and 6).  No test here depends on the
machine's speed: the slow stage is simulated by one that waits until the heartbeat has spoken."""

from __future__ import annotations

import re
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from bench.studies import sampling
from bench.run.heartbeat import Heartbeat
from tests.conftest import HANG_GUARD_S

ROOT = Path(__file__).resolve().parent.parent


def bench(*args):
    return subprocess.run([sys.executable, "-m", "bench", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=HANG_GUARD_S)


class Recorder:
    """A progress callback that records lines and lets a test wait for the k-th 'still running'."""

    def __init__(self):
        self.lines: list[str] = []
        self._cond = threading.Condition()

    def __call__(self, line: str) -> None:
        with self._cond:
            self.lines.append(line)
            self._cond.notify_all()

    def wait_for_beats(self, k: int) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: sum("still running" in ln for ln in self.lines) >= k, timeout=120)


def test_heartbeat_announces_a_stage_and_keeps_saying_it():
    rec = Recorder()
    with Heartbeat(rec, every_s=0.01) as beat:
        beat.stage("stage A")
        assert rec.wait_for_beats(2)
        beat.say("A: done")
    n = len(rec.lines)
    assert rec.lines[0] == "stage A" and "A: done" in rec.lines
    assert all(re.fullmatch(r"stage A: still running, \d+ s", ln) for ln in rec.lines if "still" in ln)
    threading.Event().wait(0.05)
    assert len(rec.lines) == n  # silent once the block is left
    with pytest.raises(ValueError, match="every_s"):
        Heartbeat(rec, every_s=0)


def test_sampling_is_not_silent_while_its_reference_integral_runs(monkeypatch):
    """Finding 6: ``sampling --case mesh.torus.camera.16x16`` printed nothing for 8 of its 8.5
    minutes, the reference integral's time.  Now a line says the integral starts and lines keep
    coming while it runs (here: until two have come, then it gives up with a planted error)."""
    rec = Recorder()

    class SlowReference:
        def __init__(self, *a, **k):
            assert rec.wait_for_beats(2), rec.lines
            raise RuntimeError("planted: stop after the beats")

    monkeypatch.setattr(sampling, "ColourErrors", SlowReference)
    with pytest.raises(RuntimeError, match="planted"):
        sampling.sampling_table(["sphere.camera.64x64"], (1e-2,), max_rays=4, progress=rec, every_s=0.01)
    assert rec.lines[0].startswith("sampling sphere.camera.64x64 (1/1): the rendering integral on 4 rays")
    assert any(ln.startswith("sampling sphere.camera.64x64 (1/1): the rendering integral") and "still running" in ln
               for ln in rec.lines[1:])


def test_sampling_prints_progress_lines_from_the_cli():
    p = bench("sampling", "--case", "sphere.camera.64x64", "--max-rays", "2", "--targets", "1e-1", "--n-max", "8")
    assert p.returncode == 0, p.stdout + p.stderr
    lines = p.stdout.splitlines()
    first_table = next(i for i, ln in enumerate(lines) if ln.startswith("| case"))
    stages = [ln for ln in lines[:first_table] if re.match(r"\[ *\d+\.\d s\] sampling sphere\.camera\.64x64", ln)]
    assert stages and "the rendering integral on 2 rays" in stages[0], p.stdout
    assert any("uniform: done" in ln for ln in stages)


def test_extract_announces_each_configuration_before_it_runs(tmp_path):
    p = bench("extract", "--case", "sphere.camera.64x64", "--resolution", "8", "--repeats", "1", "--out",
              str(tmp_path / "x"))
    assert p.returncode == 0, p.stdout + p.stderr
    lines = p.stdout.splitlines()
    start = next(i for i, ln in enumerate(lines) if "N=8: φ on 8³ points" in ln)
    done = next(i for i, ln in enumerate(lines) if re.search(r"N=8: H [\d.e-]+, C", ln))
    assert start < done


@pytest.mark.parametrize("argv,names", [
    (["sampling", "--case", "sphere.camera.64x64", "--sharpness", "nan", "--max-rays", "4"], "--sharpness"),
    (["sampling", "--case", "sphere.camera.64x64", "--sharpness", "-1", "--max-rays", "4"], "--sharpness"),
    (["sampling", "--case", ""], "--case"),
    (["sampling", "--case", "sphere.camera.64x64,nosuch.case"], "--case"),
    (["sampling", "--targets", ""], "--targets"),
    (["sampling", "--targets", "inf"], "--targets"),
    (["sampling", "--targets", "nan"], "--targets"),
    (["sampling", "--max-rays", "0"], "--max-rays"),
    (["extract", "--case", "nosuch.*"], "--case"),
    (["extract", "--resolution", "2"], "--resolution"),
], ids=lambda v: " ".join(v) if isinstance(v, list) else v)
def test_study_commands_bad_arguments_are_one_error_line(argv, names):
    """Finding 5: ``sampling --sharpness nan`` ended in a bench.run.references.NotApplicable traceback."""
    p = bench(*argv)
    assert p.returncode == 2, (p.returncode, p.stdout[-1500:], p.stderr[-1500:])
    assert "Traceback" not in p.stdout + p.stderr, p.stderr
    errors = [ln for ln in p.stderr.splitlines() if re.search(r"(^|: )error: ", ln)]
    assert len(errors) == 1 and names in errors[0], p.stderr
