"""``bench run``'s accuracy-only stages (the stability stage, the claims ledger) in a second
process, beside the timed configurations, where the machine has a core for it.

Why: neither stage reads the configurations' rows (the stability stage is a plan of its own,
written to ``stability/``; the claims write ``claims.csv`` and their plots), and neither is
timed (accuracy only), so where they run changes no number they report.  Run one after the
other they are about a third of a quick run's wall time.  Every library already runs
``--threads`` threads per process (:func:`bench.run.environment.configure_threads`), so with at
least twice that many cores the second process has cores of its own and the configurations'
timings keep theirs; with fewer (or with ``--cluster``/``--scheduler``, whose executor lives in
the first process) the stages run after the configurations, as before.  environment.json
records which (``side_stages``).

Contract: the report is written after both finish; the second process writes only its own files
(``stability/``, ``claims.csv``, ``claim_*.png``), each atomically as it goes (the runner's and
the ledger's own writes), so a process that dies keeps what it finished; a stage that fails,
or a second process that dies or cannot start, is a note in environment.json and the report
(``stability``/``claims``), never the run's end.  The child is started with ``spawn`` (a fresh
interpreter: no forked copy of a half-imported torch/jax/XLA thread pool) and terminated if the
first process leaves early (``close``).
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import time
from pathlib import Path

from ._common import (configure_process, make_console, reference_cache_dir, resolve_backends, run_claims_into,
                      split)
from ..run.environment import usable_cores
from ._run_stages import run_stability_into
from ..report.tables import STABILITY_DIR
from ..run.supervise import die_with_parent

#: environment.json's ``side_stages`` values
CONCURRENT, SEQUENTIAL = "second process, beside the configurations", "after the configurations"


def concurrent_ok(args, executor, cores: int | None = None) -> bool:
    """Whether the side stages may run beside the configurations: no cluster executor (its
    client is this process) and a core for each process's ``--threads`` threads."""
    cores = usable_cores() if cores is None else cores
    return executor is None and cores >= 2 * max(int(args.threads), 1)


def stages_main(args: argparse.Namespace, out: str, stability_suite: str | None, claims: bool, quick: bool) -> dict:
    """The side stages, as the second process runs them: threads, caches and allocator as the
    first process set them, the same backends and user cases; returns the notes
    ``{"stability": …, "claims": …}`` ("" = it ran) of the stages asked for."""
    from impls import registry

    from ..run.suites import get_suite
    from ._common import load_user_cases

    configure_process(args)
    console = make_console()
    notes = {}
    err = load_user_cases(args)
    if stability_suite is not None:
        if err:
            notes["stability"] = f"stability stage failed: {err}"
        else:
            backends, msg = resolve_backends(split(args.backend) or registry.default_ids(), args.threads, specs={})
            notes["stability"] = (f"stability stage failed: {msg}" if msg else
                                  run_stability_into(Path(out), get_suite(stability_suite), backends, args, console))
    if claims:
        notes["claims"] = run_claims_into(Path(out), quick=quick, console=console,
                                          reference_dir=reference_cache_dir(args))
    return notes


def serve_main(args: argparse.Namespace, share) -> None:
    """The second process after its stages: the configurations it claims from the run's plan
    (:func:`bench.run.sharing.serve`), with the same backends as the first process."""
    from impls import registry

    from ..run.sharing import serve

    backends, msg = resolve_backends(split(args.backend) or registry.default_ids(), args.threads, specs={})
    if msg:  # the first process resolved them, so this does not happen; if it does, it runs them itself
        raise RuntimeError(msg)
    serve(share, backends)


def _child(conn, target, arguments, parent: int, then=None) -> None:
    """The second process's entry: run ``target(*arguments)`` and send back its notes (or the
    exception that escaped it, as text), then ``then[0](*then[1])`` (the configurations it joins,
    :func:`serve_main`).  On Linux it asks to be sent SIGTERM when the first process dies
    (``PR_SET_PDEATHSIG``), so a killed run leaves no stage writing its directory behind
    (``--resume`` may then take it over)."""
    die_with_parent(parent)
    try:
        got = target(*arguments)
    except BaseException as exc:  # noqa: BLE001 - whatever happens here is a note, never the run's end
        got = {"error": f"{type(exc).__name__}: {exc}"}
    conn.send(got)
    conn.close()
    if then is not None:
        # a failure here loses nothing: the first process runs whatever this one did not report
        then[0](*then[1])


class SideStages:
    """``target(*arguments)`` (default :func:`stages_main`) in a spawned process; :meth:`wait`
    gives its notes, each stage asked for (``stages``) with a note saying why when the process
    failed to start, raised or died."""

    def __init__(self, stages: tuple[str, ...], arguments: tuple, target=stages_main, share=None):
        self.stages, self.arguments, self.target = stages, arguments, target
        self.share = share  # a bench.run.sharing.PlanShare: the process joins the configurations after its stages
        self.process = self.conn = None
        self.start_error = ""
        self.waited = False
        self.restarts = 0  # how many processes before this one died inside the stability stage

    def start(self) -> "SideStages":
        ctx = multiprocessing.get_context("spawn")
        receive, send = ctx.Pipe(duplex=False)
        try:
            then = None if self.share is None else (serve_main, (self.arguments[0], self.share))
            self.process = ctx.Process(target=_child, args=(send, self.target, self.arguments, os.getpid(), then),
                                       name="isobench-side-stages", daemon=True)
            self.process.start()
        except Exception as exc:  # noqa: BLE001 - e.g. no more processes: the notes say so
            self.start_error = f"{type(exc).__name__}: {exc}"
            self.process = None
        send.close()
        self.conn = receive
        return self

    def wait(self) -> dict[str, str]:
        """Block until the second process has sent its notes (and, where it shares the plan, the
        run has every row: the caller waits for those); its notes, one per stage asked for.  Its
        exit is not waited for here (:meth:`close` ends it): a process holding torch, jax and
        numba takes 1–2.5 s to exit, time the report is drawn in instead."""
        got, why = {}, self.start_error and f"the second process did not start: {self.start_error}"
        if self.share is not None:
            self.share.offer(None)  # it waits for a plan: a run that offered none ended early
        if self.process is not None:
            got = self._receive()
            if not got:
                self.process.join()  # it died: its exit code says how
            self.waited = True
            if "error" in got:
                why = f"the second process raised {got.pop('error')}"
            elif not got:
                why = f"the second process died (exit code {self.process.exitcode})"
                again = self._resumed()
                if again is not None:  # a backend killed it inside the stability stage: go on past that one
                    print(f"{why} while running {again[1]} in the stability stage: that configuration is recorded as "
                          "failed and the stages go on in a new process", flush=True)
                    return again[0].wait()
        return {s: str(got[s]) if s in got else f"{s} failed: {why}" for s in self.stages}

    def _receive(self) -> dict:
        """The second process's notes, or {} when it died; a configuration of its stability stage
        hung in native code is marked so and the process killed (:func:`bench.run.supervise.kill_if_hung`;
        then {}: :meth:`_resumed` goes on past it)."""
        from ..run.supervise import POLL_S, kill_if_hung

        try:
            while not self.conn.poll(POLL_S):
                kill_if_hung(self._note(), self.process.pid, self.process.kill, "the stability stage's process")
            return self.conn.recv()  # what the child sent, or EOFError when it died
        except (EOFError, OSError):
            return {}

    def _note(self) -> Path | None:
        """The stability stage's in-flight note (:data:`bench.run.supervise.INFLIGHT`), or None
        where this process runs another target."""
        from ..run.supervise import INFLIGHT

        return Path(self.arguments[1]) / STABILITY_DIR / INFLIGHT if self.target is stages_main else None

    def _resumed(self):
        """After this process died inside a configuration of the stability stage (its runner's
        in-flight note is there, :meth:`_note`): ``(the stages started again in
        a new process, resuming the stability stage, which records that configuration as failed,
        what it was)``; None otherwise, or after :data:`bench.run.supervise.MAX_RESTARTS` restarts."""
        from ..run.supervise import MAX_RESTARTS, read_note

        path = self._note()
        note = read_note(path) if path is not None else None
        if note is None or "stability" not in self.stages or self.restarts >= MAX_RESTARTS:
            return None
        what = note.get("what", "a configuration")
        args = argparse.Namespace(**{**vars(self.arguments[0]), "resume": True})
        again = SideStages(self.stages, (args,) + tuple(self.arguments[1:]), target=self.target)
        again.restarts = self.restarts + 1
        self.close()
        return again.start(), what

    def alive(self) -> bool:
        """Whether the second process is running."""
        return self.process is not None and self.process.is_alive()

    def kill(self) -> None:
        """Kill the second process (a configuration it runs for the plan hung in native code:
        :class:`bench.run.sharing.SharingExecutor`)."""
        if self.process is not None:
            self.process.kill()

    def close(self) -> None:
        """After :meth:`wait`, let the second process end (reading its last messages, which the run
        no longer needs, so that its queue's feeder can finish) for up to 10 s; terminate it if it
        is still running then, or at once when the first process leaves early (no :meth:`wait`)."""
        if self.process is not None and self.process.is_alive() and self.waited:
            deadline = time.monotonic() + 10.0
            while self.process.is_alive() and time.monotonic() < deadline:
                if self.share is not None:
                    self.share.receive(0.1)
                else:
                    self.process.join(0.1)
        if self.process is not None and self.process.is_alive():
            self.process.terminate()
            self.process.join(5)
        if self.conn is not None:
            self.conn.close()
