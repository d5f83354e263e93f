"""``bench run``'s accuracy-only stages in a second process (bench/commands/_side_stages.py), and
the warm-up call kept only for backends that compile (bench/run/configuration.py)."""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from bench.commands._side_stages import SideStages, concurrent_ok
from bench.run.configuration import warmup_policy
from bench.run.timing import TimingPolicy
from tests.conftest import HANG_GUARD_S


def notes_of(kind: str) -> dict:
    """A side-stage target (module level: the spawned process imports it by name)."""
    if kind == "ok":
        return {"stability": "", "claims": "claims failed: planted"}
    if kind == "raise":
        raise RuntimeError("planted")
    if kind == "die":
        os._exit(3)
    if kind == "sleep":
        time.sleep(3600)
    return {}


def test_side_stages_return_their_notes():
    side = SideStages(("stability", "claims"), ("ok",), target=notes_of).start()
    try:
        assert side.wait() == {"stability": "", "claims": "claims failed: planted"}
    finally:
        side.close()


def test_a_stage_process_that_raises_or_dies_is_a_note_for_each_stage_not_the_runs_end():
    for kind, said in (("raise", "raised RuntimeError: planted"), ("die", "died (exit code 3)")):
        side = SideStages(("stability", "claims"), (kind,), target=notes_of).start()
        try:
            got = side.wait()
        finally:
            side.close()
        assert set(got) == {"stability", "claims"}
        assert all(v.startswith(f"{s} failed: the second process {said}") for s, v in got.items()), got


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie, dead but not yet reaped by whoever adopted it, does not)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_the_stage_process_ends_when_the_run_process_is_killed():
    """A killed run leaves no stage process writing its directory (a --resume may take it over)."""
    code = ("import os, sys; from bench.commands._side_stages import SideStages; "
            "from tests.test_side_stages import notes_of; "
            "s = SideStages(('stability',), ('sleep',), target=notes_of).start(); "
            "print(s.process.pid, flush=True); sys.stdin.readline(); os._exit(0)")
    root = Path(__file__).resolve().parent.parent
    p = subprocess.Popen([sys.executable, "-c", code], cwd=root, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                         env={**os.environ, "PYTHONPATH": str(root)})
    child = int(p.stdout.readline())
    assert _alive(child)  # alive while its parent is
    p.stdin.write("\n")
    p.stdin.flush()
    p.wait(timeout=HANG_GUARD_S)
    deadline = time.monotonic() + HANG_GUARD_S  # a guard against a hang, not a measure of speed
    while time.monotonic() < deadline:
        if not _alive(child):
            return
        time.sleep(0.2)
    pytest.fail(f"the stage process {child} outlived its parent")


def test_side_stages_run_beside_the_configurations_only_with_a_core_each_and_no_cluster():
    one = argparse.Namespace(threads=1)
    assert concurrent_ok(one, None, cores=2)
    assert not concurrent_ok(one, None, cores=1)
    assert not concurrent_ok(argparse.Namespace(threads=2), None, cores=3)
    assert not concurrent_ok(one, object(), cores=8)  # a cluster executor: its client is this process


class _Caps:
    def __init__(self, jit):
        self.jit = jit


class _Backend:
    def __init__(self, jit):
        self.capabilities = _Caps(jit)


class _Broken:
    @property
    def capabilities(self):
        raise RuntimeError("broken")


def test_the_warmup_call_is_kept_for_backends_that_compile_only():
    pol = TimingPolicy(warmup=1)
    assert warmup_policy(_Backend(True), pol).warmup == 1
    assert warmup_policy(_Backend(False), pol).warmup == 0
    assert warmup_policy(_Broken(), pol).warmup == 1  # unknown: counted as compiling
    assert warmup_policy(object(), pol).warmup == 1
    assert warmup_policy(_Backend(False), pol).min_repeats == pol.min_repeats  # the samples are untouched


def test_a_long_first_call_stands_in_for_the_warmup_only_where_the_compile_was_reported_apart():
    """A kernel that reports its compile (``Prepared.compile_s``) keeps ``warm_after_s``; one that
    does not may compile inside its first call and warm up after it (a lazy JIT): ∞, its warm-up
    call is always made."""
    pol = TimingPolicy(warmup=1, warm_after_s=0.05)
    assert warmup_policy(_Backend(True), pol, compile_s=0.3).warm_after_s == 0.05
    assert warmup_policy(_Backend(True), pol, compile_s=0.0).warm_after_s == 0.05
    assert warmup_policy(_Backend(True), pol, compile_s=None).warm_after_s == math.inf
    assert warmup_policy(_Broken(), pol).warm_after_s == math.inf
    assert warmup_policy(_Backend(False), pol, compile_s=None).warmup == 0  # warm after its first call anyway
