"""A run directory has one writer, and ``--out`` is new, empty or (with ``--resume``) a run's
(issue 33, findings 2, 4 and 5): ``bench.run.rundir`` and the CLI paths that use it."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from bench.run.rundir import LOCK_FILE, LockHeld, OutError, RunLock, claim_out
from tests.conftest import HANG_GUARD_S

ROOT = Path(__file__).resolve().parent.parent
ONE = ["--case", "sphere.camera.64x64", "--method", "sphere_trace", "--backend", "numpy", "--accuracy-only",
       "--no-claims", "--no-progress"]


def bench(*args, timeout=HANG_GUARD_S):
    return subprocess.run([sys.executable, "-m", "bench", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout)


def one_error_line(p, code: int, names: str) -> None:
    assert p.returncode == code, (p.returncode, p.stdout[-2000:], p.stderr[-2000:])
    assert "Traceback" not in p.stdout + p.stderr, p.stderr
    errors = [ln for ln in p.stderr.splitlines() if re.search(r"(^|: )error: ", ln)]
    assert len(errors) == 1 and names in errors[0], p.stderr


def test_the_lock_is_exclusive_records_its_holder_and_is_freed(tmp_path):
    first = RunLock(tmp_path).acquire()
    rec = json.loads((tmp_path / LOCK_FILE).read_text())
    assert rec["pid"] == os.getpid() and rec["host"] and rec["started"]
    with pytest.raises(LockHeld, match=rf"being written by pid {os.getpid()} on "):
        RunLock(tmp_path).acquire()  # another open file description: refused even in this process
    first.release()
    first.release()  # idempotent
    with RunLock(tmp_path):
        pass


def test_a_new_run_into_a_directory_in_use_names_its_holder(tmp_path):
    """A second ``bench run`` into a run directory another process is writing (no --resume) was
    refused as "not empty" (the files the holder writes), where the README promises the holder
    named; with --resume it was.  Now both name it."""
    first = RunLock(tmp_path).acquire()
    (tmp_path / "results.csv").write_text("x\n")
    try:
        for resume in (False, True):
            with pytest.raises(LockHeld, match=rf"being written by pid {os.getpid()} on "):
                claim_out(tmp_path, resume=resume)
    finally:
        first.release()
    with pytest.raises(OutError, match="is not empty"):  # (no holder: what it holds is named)
        claim_out(tmp_path)


def test_a_holder_that_has_not_recorded_itself_yet_is_named_as_still_starting(tmp_path):
    """Between a holder's flock and its record the lock file is empty: a second process is refused
    all the same, told the holder is still starting (two runs started together meet this window
    under load: the race test below)."""
    import fcntl

    fd = os.open(tmp_path / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        with pytest.raises(LockHeld, match=r"being written by another process \(still starting"):
            RunLock(tmp_path).acquire()
    finally:
        os.close(fd)


def test_a_record_left_by_an_ended_holder_is_not_named_as_the_holder(tmp_path):
    """The lock file keeps the last holder's record; a process refused before the new holder has
    rewritten it is not told that the ended process holds the run directory."""
    import fcntl
    import socket

    # a pid above the kernel's largest: no process has it, and none can take it while the test runs
    # (an ended child's pid could be handed to another process)
    ended = int(Path("/proc/sys/kernel/pid_max").read_text()) + 1 if Path("/proc/sys/kernel/pid_max").exists() \
        else 2 ** 22 + 1
    (tmp_path / LOCK_FILE).write_text(json.dumps({"pid": ended, "host": socket.gethostname(),
                                                  "started": "2026-01-01T00:00:00+00:00", "command": "old run"}))
    fd = os.open(tmp_path / LOCK_FILE, os.O_RDWR)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # the new holder, before its record
        with pytest.raises(LockHeld, match=r"another process \(still starting") as err:
            RunLock(tmp_path).acquire()
        assert f"pid {ended}" not in str(err.value)
    finally:
        os.close(fd)


def test_a_killed_holder_leaves_no_stale_lock(tmp_path):
    code = (f"from bench.run.rundir import RunLock; import sys, time; RunLock({str(tmp_path)!r}).acquire(); "
            "print('locked', flush=True); time.sleep(600)")
    p = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    try:
        assert p.stdout.readline().strip() == "locked"
        with pytest.raises(LockHeld, match=f"pid {p.pid}"):
            RunLock(tmp_path).acquire()
    finally:
        p.send_signal(signal.SIGKILL)
        p.wait(timeout=60)
    RunLock(tmp_path).acquire().release()  # the kernel dropped the dead holder's lock


@pytest.mark.parametrize("extra", [[], ["--resume"], ["--cluster", "local:1"]],
                         ids=["new run", "resume", "cluster run"])
def test_a_second_process_is_refused_naming_the_holder(tmp_path, extra):
    """Finding 2: two runs into one --out both succeeded.  Now the holder is named, whatever the
    kind of run; the refused process writes nothing."""
    out = tmp_path / "run"
    if extra == ["--resume"]:
        assert bench("run", "--out", str(out), *ONE).returncode == 0
    else:
        out.mkdir()
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.name != LOCK_FILE}
    with RunLock(out):
        p = bench("run", "--out", str(out), *ONE, *extra)
    one_error_line(p, 2, f"is being written by pid {os.getpid()}")
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.name != LOCK_FILE} == before


def test_two_runs_started_together_into_one_out_one_wins(tmp_path):
    """Finding 2, raced for real: exactly one succeeds; the other is refused (by the lock while
    the winner runs, or by the winner's files after it), and the results are the winner's."""
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "bench", "run", "--out", str(out), *ONE]
    procs = [subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for _ in range(2)]
    results = [(p.wait(timeout=HANG_GUARD_S), p.stderr.read()) for p in procs]
    codes = sorted(rc for rc, _ in results)
    assert codes == [0, 2], results
    loser = next(err for rc, err in results if rc == 2)
    # refused by the lock (the holder named by its record, or, when the loser looks between the
    # winner's flock and its record, as still starting) or by the winner's files after it
    assert "Traceback" not in loser and ("is being written by pid" in loser or "is not empty" in loser
                                         or "is being written by another process (still starting" in loser), loser
    env = json.loads((out / "environment.json").read_text())
    assert env["complete"] == "true"


def test_a_foreign_directory_is_refused_and_left_untouched(tmp_path):
    """Finding 4: a folder holding someone's report.html (no results) was accepted and the file
    overwritten."""
    out = tmp_path / "theirs"
    out.mkdir()
    (out / "report.html").write_text("someone's report")
    p = bench("run", "--out", str(out), *ONE)
    one_error_line(p, 2, "--out")
    assert "report.html" in p.stderr and "not empty" in p.stderr
    assert sorted(x.name for x in out.iterdir()) == ["report.html"]  # not even a lock file
    assert (out / "report.html").read_text() == "someone's report"
    with pytest.raises(OutError, match="holds report.html"):
        claim_out(out)


def test_an_empty_directory_is_accepted_and_resume_needs_a_directory(tmp_path):
    lock = claim_out(tmp_path / "new")  # absent: created
    lock.release()
    claim_out(tmp_path / "new").release()  # only its lock file in it: still empty
    with pytest.raises(OutError, match="no run to --resume"):
        claim_out(tmp_path / "absent", resume=True)
    assert not (tmp_path / "absent").exists()


@pytest.mark.parametrize("target", ["proc", "under a file", "a file"])
def test_out_paths_that_cannot_be_directories_are_one_error_line(tmp_path, target):
    """Finding 5: FileNotFoundError / NotADirectoryError tracebacks from bench/run/results.py."""
    (tmp_path / "f").write_text("x")
    out = {"proc": "/proc/isobench-x", "under a file": str(tmp_path / "f" / "sub"), "a file": str(tmp_path / "f")}
    p = bench("run", "--out", out[target], *ONE)
    one_error_line(p, 2, "--out")


@pytest.mark.parametrize("argv", [
    lambda t: ["extract", "--case", "sphere.camera.64x64", "--resolution", "8", "--out", str(t / "f" / "sub")],
    lambda t: ["claims", "--only", "3", "--out", str(t / "f" / "sub")],
    lambda t: ["compare", str(ROOT / "reports" / "baseline"), str(ROOT / "reports" / "baseline"), "--out",
               str(t / "f" / "sub.csv")],
    lambda t: ["speed", "--backend", "numpy", "--side", "4", "--no-peers", "--repeats", "1", "--out",
               str(t / "f" / "sub.json")],
], ids=["extract", "claims", "compare", "speed"])
def test_other_commands_out_paths_are_one_error_line(tmp_path, argv):
    (tmp_path / "f").write_text("x")
    one_error_line(bench(*argv(tmp_path)), 2, "--out")
