"""``python -m bench run`` as a supervisor of the process that runs it, so that a backend that
kills its process (a segfault or an abort in a native library, an ``os._exit``) costs its own
configuration and no other row.

A configuration's Python exceptions, contract breaches and hangs are failed rows already
(:func:`bench.run.configuration.run_one`); a process that dies cannot write one.  So the command
runs in a child process (environment :data:`SUPERVISED_ENV` set), and the runner keeps a note of
the configuration in flight in the run directory (:data:`INFLIGHT`, removed as each configuration
ends and when the runner stops by any Python path).  When the child dies with
that note present, this process says so and starts the same command again with
``--resume --out DIR``: the resumed runner records the noted configuration as a failed row
("Crashed: …") and runs the rest; rows written before the death are kept (the runner rewrites them
at least every few seconds: :data:`bench.run.runner.FLUSH_COST_FACTOR`).  Each restart passes at
least the configuration that crashed, so it ends; :data:`MAX_RESTARTS` bounds it anyway.

Restarted: a child that ends, whatever its exit status (0 too: a backend's ``os._exit(0)``), with
a note it wrote itself (the note's ``pid``) still there: the runner removes the note as each
configuration ends and on every Python path out of it, so only a process that died inside a
configuration leaves its own note.  Not restarted: an exit without such a note (the command
ended, whatever its status; a note an earlier process left, which the child did not get as far
as taking over, restarts nothing), and a child stopped by SIGINT or SIGTERM (the user's or the
machine's stop, which this process passes on).  A library user calling
:func:`bench.commands.main` in-process is not supervised.

The child runs in a session of its own, so that a configuration killed as hung (below) takes the
processes its backend started with it (its process group; a helper that starts a session of its
own escapes this); the terminal's Ctrl-C then reaches this process only, which passes SIGINT on to
the child's process group, as the terminal did, and SIGTERM likewise.

Hangs: ``--timeout`` interrupts Python code at once and a compiled kernel when it returns to
Python (:func:`bench.run.timing.time_limit`).  The note carries that limit; a configuration that
has run :data:`HUNG_AFTER` past it is inside native code that does not return, and its process is
killed (:func:`kill_if_hung`): by this process for the run's own (with its process group), by the first process
for the second's share of the plan (:class:`bench.run.sharing.SharingExecutor`), by the side
stages' waiter for the stability stage; on a cluster the client cancels the task and restarts its
worker (:class:`bench.run.cluster.ClusterExecutor`).  Each is a ``Timeout`` row.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

#: the run directory's note of the configuration its process is running, written as it starts and
#: removed as it ends (:class:`bench.run.runner._InFlight`): after a process that died inside a
#: backend (a segfault, an abort, an ``os._exit``) it names the configuration that killed it, and
#: the resumed run records that one as failed instead of running it again
INFLIGHT = "inflight.json"
#: set in the child's environment: the command runs there, unsupervised
SUPERVISED_ENV = "ISOBENCH_SUPERVISED"
#: the file where the child writes the run directory it claimed (``bench run`` chooses it)
OUT_NOTE_ENV = "ISOBENCH_OUT_NOTE"
#: the supervisor's pid, in the child's environment (:func:`die_with_parent`)
PARENT_ENV = "ISOBENCH_SUPERVISOR_PID"
#: where the side stages' runner keeps its own note (``bench.report.tables.STABILITY_DIR``)
SIDE_DIR = "stability"
#: seconds between two looks at the run's in-flight note
POLL_S = 1.0
#: a configuration counts as hung in native code once it has run factor × its limit + seconds
#: (:func:`overdue`): past the limit by as much again and a minute, so that a kernel that returns
#: late is interrupted as usual and the accuracy measurement after the timed part (outside the
#: limit) has time to finish
HUNG_AFTER = (2.0, 60.0)
#: ``factor,seconds`` replacing :data:`HUNG_AFTER` (tests/test_crash_isolation.py: not to wait a minute)
HUNG_AFTER_ENV = "ISOBENCH_HUNG_AFTER"
#: restarts after crashes, at most, per command
MAX_RESTARTS = 50
#: the child's exit statuses that mean it was stopped, not that it crashed
_STOPPED = {-signal.SIGINT, -signal.SIGTERM, 128 + signal.SIGINT, 128 + signal.SIGTERM}


def wanted(argv: list[str]) -> bool:
    """Whether ``python -m bench <argv>`` runs supervised: the ``run`` command, not already in a
    supervised child, and not asking for help."""
    return (argv[:1] == ["run"] and os.environ.get(SUPERVISED_ENV) != "1"
            and not {"-h", "--help"} & set(argv[1:]))


def die_with_parent(parent: int) -> None:
    """``prctl(PR_SET_PDEATHSIG, SIGTERM)`` where the C library has it (Linux; else nothing), and
    exit at once if ``parent`` already died before it was set (this process was then adopted):
    a supervised run, or the side stages' process, does not outlive the process that started it."""
    import ctypes

    try:
        ctypes.CDLL(None).prctl(1, int(signal.SIGTERM))  # 1: PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    if os.getppid() != parent:
        os._exit(1)


def note_out(out: Path) -> None:
    """In a supervised child: tell the supervisor which run directory this run claimed."""
    where = os.environ.get(OUT_NOTE_ENV)
    if where:
        Path(where).write_text(str(Path(out).resolve()))


def _has(argv: list[str], flag: str) -> bool:
    return any(a == flag or a.startswith(flag + "=") for a in argv)


def _status(code: int) -> str:
    if code < 0:
        try:
            return f"signal {signal.Signals(-code).name}"
        except ValueError:
            return f"signal {-code}"
    return f"exit status {code}"


def read_note(path: Path) -> dict | None:
    """The in-flight note at ``path`` (:data:`INFLIGHT`), or None (none, or unreadable)."""
    try:
        note = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None
    return note if isinstance(note, dict) else None


def overdue(path: Path, now: float | None = None) -> dict | None:
    """The note at ``path`` if its configuration has run past its time limit (``limit_s``, the
    run's ``--timeout``; 0: none) by more than :data:`HUNG_AFTER` allows, else None.  The limit
    interrupts Python code at once and a compiled kernel when it returns to Python
    (:func:`bench.run.timing.time_limit`); a configuration still running that long after it is
    inside native code that does not return (a hung kernel, a compile that does not end)."""
    note = read_note(path)
    if not note or "hung_s" in note:  # none, or one already killed as hung
        return None
    elapsed = hung_for(float(note.get("started", 0.0)), float(note.get("limit_s") or 0.0), now)
    return None if elapsed is None else {**note, "hung_s": elapsed}


def hung_for(started: float, limit_s: float, now: float | None = None) -> float | None:
    """Seconds since ``started`` (a ``time.time()``) if a configuration with time limit ``limit_s``
    (0: none) started then counts as hung in native code (:data:`HUNG_AFTER`), else None."""
    if not limit_s:
        return None
    elapsed = (time.time() if now is None else now) - started
    factor, extra = map(float, os.environ.get(HUNG_AFTER_ENV, "").split(",")) if os.environ.get(HUNG_AFTER_ENV) \
        else HUNG_AFTER
    return elapsed if elapsed > factor * limit_s + extra else None


def hung_reason(limit_s: float, hung_s: float) -> str:
    """The reason of a configuration's failed row after it was killed as hung."""
    return (f"Timeout: ran past the time limit of {limit_s:g} s (--timeout) in code that does not return to Python "
            f"(a native kernel or compile): its process was killed after {hung_s:.0f} s, and it is not run again")


def kill_if_hung(path: Path | None, pid: int, kill, who: str) -> bool:
    """Where the note at ``path`` is overdue (:func:`overdue`) and was written by process ``pid``
    (not a note an earlier process left): rewrite it as that of a configuration killed as hung,
    so that the resumed run records a Timeout, not a crash (:func:`bench.run.runner.crashed_rows`),
    say so on stderr naming ``who``, call ``kill()``, and return True."""
    from .results import write_json

    hung = overdue(path) if path is not None else None
    if hung is None or hung.get("pid") != pid:
        return False
    write_json(Path(path), hung)
    print(f"{who} is stuck in {hung.get('what', 'a configuration')} ({hung['hung_s']:.0f} s, its limit "
          f"{float(hung['limit_s']):g} s): killing it", file=sys.stderr, flush=True)
    kill()
    return True


def _wait_gone(pid: int, seconds: float = 10.0) -> None:
    """Until process ``pid`` (> 0; else nothing) is gone, for at most ``seconds``."""
    if pid <= 0:  # (os.kill(0 or −1, 0) would ask about a process group or every process)
        return
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except (ProcessLookupError, PermissionError):
            return
        time.sleep(0.05)


def _command(args: list[str]) -> list[str]:
    """The child's command line: ``python -m bench <args>`` (a seam for the tests)."""
    return [sys.executable, "-m", "bench", *args]


def _signal_group(proc: subprocess.Popen, signum: int) -> None:
    """Send ``signum`` to the process group of ``proc`` (the session it leads, :func:`_child`),
    or to ``proc`` alone when it has no group of its own; nothing once ``proc`` was reaped (its
    pid may then be another process's)."""
    if proc.returncode is not None:
        return
    try:
        os.killpg(proc.pid, signum)
    except (ProcessLookupError, PermissionError):  # no group led by it (it left it): the child itself
        proc.send_signal(signum)


def _child(cmd: list[str], env: dict, note_of_out) -> tuple[int, int]:
    """Run ``cmd`` (:func:`_command`) and wait for it; returns ``(exit status, its pid)``.

    The child leads a session of its own (``start_new_session``): a configuration hung in native
    code is killed with every process of that group, its backend's helpers too, not the child
    alone (they outlived the run).  A session of its own takes the child out of the terminal's
    foreground process group, so SIGINT (the terminal's Ctrl-C, which now reaches only this
    process) and SIGTERM given to this process are passed on to the child's process group, as
    the terminal or a job's ``kill`` of the group reached them before — unless this process was
    started ignoring them (a background job of a non-interactive shell ignores SIGINT): the
    child then inherits the ignored signal, and so does this process.  Every :data:`POLL_S` it
    looks at the run's in-flight note (``note_of_out()``: its path, once the child claimed a run
    directory): a configuration hung in native code is marked so and the group killed
    (:func:`kill_if_hung`)."""
    proc = subprocess.Popen(cmd, env={**env, PARENT_ENV: str(os.getpid())}, start_new_session=True)

    def forward(signum, frame):
        _signal_group(proc, signum)

    # (a signal this process was started ignoring — SIGINT in a background job of a
    # non-interactive shell, or under nohup — stays ignored: the child inherits that too)
    old_int, old_term = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    for signum, old in ((signal.SIGINT, old_int), (signal.SIGTERM, old_term)):
        if old is not signal.SIG_IGN:
            signal.signal(signum, forward)
    try:
        while True:
            try:
                return proc.wait(timeout=POLL_S), proc.pid
            except subprocess.TimeoutExpired:
                pass
            kill_if_hung(note_of_out(), proc.pid, lambda: _signal_group(proc, signal.SIGKILL), "the run's process")
    finally:
        signal.signal(signal.SIGINT, old_int)
        signal.signal(signal.SIGTERM, old_term)


def supervise(argv: list[str]) -> int:
    """Run ``bench <argv>`` (a ``run`` command) in a child; after a crash inside a configuration,
    resume it (module docstring).  Returns the exit status to end with."""
    fd, note = tempfile.mkstemp(prefix="isobench-out-", suffix=".txt")
    os.close(fd)
    env = {**os.environ, SUPERVISED_ENV: "1", OUT_NOTE_ENV: note}
    args = list(argv)

    def out_dir() -> Path | None:
        text = Path(note).read_text().strip()
        return Path(text) if text else None

    def note_of_out() -> Path | None:
        out = out_dir()
        return None if out is None else out / INFLIGHT

    try:
        for restart in range(MAX_RESTARTS + 1):
            code, pid = _child(_command(args), env, note_of_out)
            out = out_dir()
            # died inside a configuration: its own note is left, whatever the exit status (a
            # backend's os._exit(0) too); a note of an earlier process it never took over is not its
            left = read_note(out / INFLIGHT) if out is not None else None
            if code in _STOPPED or left is None or left.get("pid") != pid:
                return code if code >= 0 else 128 - code
            # the side stages' process died with this one (PR_SET_PDEATHSIG): what it was running is
            # not to blame, and the resumed stability stage must not record it as crashed
            side = read_note(out / SIDE_DIR / INFLIGHT)
            if side is not None:
                _wait_gone(int(side.get("pid") or 0))
                (out / SIDE_DIR / INFLIGHT).unlink(missing_ok=True)
            what = left.get("what", "a configuration")
            if left.get("planning"):  # a user field at planning: the resumed plan skips its case, with this
                from .results import write_json

                write_json(out / INFLIGHT, {**left, "status": _status(code)})
            if restart == MAX_RESTARTS:
                print(f"the run's process died ({_status(code)}) while running {what}, after {MAX_RESTARTS} restarts; "
                      f"stopping: finish it with --resume --out {out}", file=sys.stderr, flush=True)
                return 1
            print(f"the run's process died ({_status(code)}) while running {what}: "
                  + ("that case's rows are skipped with the reason" if left.get("planning") else
                     "that configuration is recorded as failed")
                  + f" and the run goes on (--resume --out {out})", file=sys.stderr, flush=True)
            args = list(argv) + ([] if _has(argv, "--resume") else ["--resume"]) + \
                ([] if _has(argv, "--out") else ["--out", str(out)])
        return 1  # pragma: no cover - the loop returns
    finally:
        Path(note).unlink(missing_ok=True)
