"""``python -m bench run`` as a supervisor of the process that runs it, so that a backend that
kills its process (a segfault or an abort in a native library, an ``os._exit``) costs its own
configuration and no other row.

A configuration's Python exceptions, contract breaches and hangs are failed rows already
(:func:`bench.run.configuration.run_one`); a process that dies cannot write one.  So the command
runs in a child process (environment :data:`SUPERVISED_ENV` set), and the runner keeps a note of
the configuration in flight in the run directory (:data:`bench.run.runner.INFLIGHT`, removed as
each configuration ends and when the runner stops by any Python path).  When the child dies with
that note present, this process says so and starts the same command again with
``--resume --out DIR``: the resumed runner records the noted configuration as a failed row
("Crashed: …") and runs the rest; rows written before the death are kept (the runner rewrites them
at least every few seconds: :data:`bench.run.runner.FLUSH_COST_FACTOR`).  Each restart passes at
least the configuration that crashed, so it ends; :data:`MAX_RESTARTS` bounds it anyway.

Not restarted: an exit without the note (the command ended, whatever its status), and a child
stopped by SIGINT or SIGTERM (the user's or the machine's stop, which this process passes on).
A library user calling :func:`bench.commands.main` in-process is not supervised.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
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


def _child(argv: list[str], env: dict) -> int:
    """Run ``python -m bench <argv>`` and wait for it; SIGTERM given to this process is passed
    on, SIGINT (a terminal's Ctrl-C reaches both) left to the child."""
    proc = subprocess.Popen([sys.executable, "-m", "bench", *argv], env={**env, PARENT_ENV: str(os.getpid())})

    def forward(signum, frame):
        proc.send_signal(signum)

    old_int = signal.signal(signal.SIGINT, signal.SIG_IGN)
    old_term = signal.signal(signal.SIGTERM, forward)
    try:
        return proc.wait()
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
    try:
        for restart in range(MAX_RESTARTS + 1):
            code = _child(args, env)
            text = Path(note).read_text().strip()
            out = Path(text) if text else None
            if code == 0 or code in _STOPPED or out is None or not (out / INFLIGHT).exists():
                return code if code >= 0 else 128 - code
            try:
                what = json.loads((out / INFLIGHT).read_text()).get("what", "?")
            except (OSError, ValueError):
                what = "a configuration"
            if restart == MAX_RESTARTS:
                print(f"the run's process died ({_status(code)}) while running {what}, after {MAX_RESTARTS} restarts; "
                      f"stopping: finish it with --resume --out {out}", file=sys.stderr, flush=True)
                return 1
            print(f"the run's process died ({_status(code)}) while running {what}: that configuration is recorded "
                  f"as failed and the run goes on (--resume --out {out})", file=sys.stderr, flush=True)
            args = list(argv) + ([] if _has(argv, "--resume") else ["--resume"]) + \
                ([] if _has(argv, "--out") else ["--out", str(out)])
        return 1  # pragma: no cover - the loop returns
    finally:
        Path(note).unlink(missing_ok=True)
