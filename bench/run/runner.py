"""The runner: plan (cases × methods × dtypes × knobs × backends), execute, record.

Every planned configuration becomes rows, never nothing: ``ok`` (measured; one row per checked
quantity, see :mod:`bench.run.metrics`), ``skipped`` (with the reason: backend unavailable,
method not implemented, dtype unsupported, scene lacks what the method needs, the backend
declines the scene (``declines`` hook or :class:`impls.protocol.Declined` from ``prepare``), no
reference answer) or ``failed`` (the exception, a wrong shape, a silent NaN or a timeout; the
run goes on).  One configuration is measured by :mod:`bench.run.configuration`; where it runs is
the :class:`bench.run.executor.Executor`'s business (this process, or a dask cluster).

Rows are written to disk atomically every ``flush_s`` seconds, or every :data:`FLUSH_COST_FACTOR`
times as long as the last write took once the table is large, so a run that dies keeps what it
finished up to that moment, and ``resume=True`` finishes it (:mod:`bench.run.resume`).
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from impls import Unavailable

from . import environment, interrupts
from .configuration import failed_rows
from .executor import InProcessExecutor, Interrupted
from .plan import CONFIG_KEY, Config, new_run_id, plan, planning_deaths, planning_in
from .references import ReferenceOptions
from .results import OVER_BUDGET, knob_string, to_frame, write_json, write_results
from .resume import check_case_versions, kept_rows, load_previous, outcome_counts, outcome_of, record_elapsed
from .sharing import SharingExecutor
from .suites import Suite
from .supervise import INFLIGHT, hung_reason, read_note
from .timing import Timeout, TimingPolicy, time_limit

__all__ = ["CONFIG_KEY", "Config", "Interrupted", "RunOptions", "new_run_id", "plan", "run"]

#: the results are rewritten whole (parquet and csv, atomically), so a write's cost grows with
#: the run, and writing every ``flush_s`` would take a growing share of a long sweep's wall time
#: (docs/performance.md).  Waiting this many times the last write's cost between writes bounds
#: writing to 1/(1 + FLUSH_COST_FACTOR) of the wall time, at the price of redoing at most that
#: interval's configurations after a kill (--resume): 30, about 3 % (docs/performance.md).
FLUSH_COST_FACTOR = 30.0

#: the reason of a configuration whose process died while it ran (:func:`crashed_rows`)
CRASHED = "Crashed"



@dataclasses.dataclass
class RunOptions:
    """How a run is planned, measured and bounded.

    ``case_pattern``, ``methods``, ``dtypes``: narrow the suite's plan (:func:`bench.run.plan.plan`).
    ``policy``: how each configuration is timed.  ``run_id``: the new run's id (default: a fresh one).
    ``resume``: ``out_dir`` holds a partial run; its rows are kept, its run id reused, and only
    the configurations it lacks are run.  ``rerun_cases`` (globs on case ids; resume only): cases
    whose content changed since the run started are run again, their old rows dropped; any other
    changed case refuses the resume (:func:`bench.run.resume.check_case_versions`).
    ``budget_s`` (None: none): a wall-clock guard against a hang, not a plan: each configuration
    is limited to the smaller of ``policy.timeout_s`` and the budget left, and once it is spent
    the configuration in flight and those left become ``skipped`` rows whose reason starts with
    :data:`OVER_BUDGET`; environment.json then says ``complete: "false"`` with
    ``incomplete_reason``, and ``bench compare`` refuses to gate on it (``--resume``, with a
    larger budget or none, finishes them).  ``rounds``: the whole plan is timed ``rounds``
    times, round after round, and each configuration's samples pooled, so slow drift of a shared
    machine's load shows up as spread within a configuration instead of as a difference between
    runs.  ``reference_cache_dir``: where costly reference answers are kept across runs (None:
    not kept); ``reference_timeout_s``: limit on one costly reference computation.
    ``executor`` (None: :class:`bench.run.executor.InProcessExecutor`): where the configurations
    run.  ``share`` (a :class:`bench.run.sharing.PlanShare` and a callable saying whether
    the second process still runs; used only without ``executor`` and with ``rounds`` 1): a
    second process joins the plan once its own stages are done
    (:class:`bench.run.sharing.SharingExecutor`).  ``env_extra``: recorded in environment.json
    as given.  ``flush_s``: the least seconds between two writes of the rows.
    """

    case_pattern: str | None = None
    methods: list[str] | None = None
    dtypes: list[str] | None = None
    policy: TimingPolicy = dataclasses.field(default_factory=TimingPolicy)
    run_id: str | None = None
    resume: bool = False
    rerun_cases: list[str] | None = None
    budget_s: float | None = None
    rounds: int = 1
    reference_cache_dir: Path | None = None
    reference_timeout_s: float = 30.0
    executor: Any = None
    share: Any = None
    env_extra: dict | None = None
    flush_s: float = 1.0

    def check(self) -> None:
        if self.rounds < 1:
            raise ValueError(f"--rounds must be ≥ 1, got {self.rounds}")
        if self.budget_s is not None and not (self.budget_s >= 0 and np.isfinite(self.budget_s)):
            raise ValueError(f"--budget must be a finite number of seconds ≥ 0, got {self.budget_s}")


#: seconds a backend's versions() may take (it reads version strings; a plug-in's that hung held
#: the run before its first row, past any --timeout)
VERSIONS_LIMIT_S = 60.0


def _versions(bid: str, backend: Any) -> dict[str, str]:
    """``backend.versions()`` as recorded in environment.json; a versions() that raises (anything
    but a Ctrl-C), runs past :data:`VERSIONS_LIMIT_S` or returns something else is recorded as
    such (the run goes on).  One that ends the process (``os._exit``, a crash) is not caught."""
    try:
        with time_limit(VERSIONS_LIMIT_S, "a backend's versions()"):
            got = backend.versions()
            if not isinstance(got, dict):
                raise TypeError(f"returned {type(got).__name__}, expected a dict of library → version")
            return {f"backend.{bid}.{k}": str(v) for k, v in got.items()}
    except BaseException as exc:  # noqa: BLE001 - a plug-in's code: whatever it raises is recorded
        if not isinstance(exc, Timeout) and not interrupts.is_fault(exc):
            raise
        return {f"backend.{bid}.versions_error": f"{type(exc).__name__}: {exc}"[:300]}



def _environment(suite: Suite, backends: dict, out_dir: Path, opts: RunOptions):
    """(environment, previous rows or None) of this session: a new run's, or the resumed run's
    marked as one more session; both marked incomplete until the run ends."""
    previous = None
    if opts.resume:
        env, previous = load_previous(out_dir)
    else:
        env = environment.collect()
        env["run_id"] = opts.run_id or new_run_id()
        env["elapsed_sessions_s"] = "[]"
    env["elapsed_sessions_s"] = json.dumps(json.loads(env["elapsed_sessions_s"]) + [0.0])
    env.update(suite=suite.name, complete="false", incomplete_reason="running (or killed): finish it with --resume",
               budget_s="none" if opts.budget_s is None else f"{opts.budget_s:g}",
               timing_policy=json.dumps(dataclasses.asdict(opts.policy), sort_keys=True))
    env.update(opts.env_extra or {})
    for bid, b in backends.items():
        if not isinstance(b, Unavailable):
            env.update(_versions(bid, b))
            if environment.driver_record(b):
                env[f"backend.{bid}.driver"] = environment.driver_record(b)
    return env, previous


class _Writer:
    """The rows and environment.json of the run directory, rewritten whole and atomically, at
    most as often as :data:`FLUSH_COST_FACTOR` allows."""

    def __init__(self, out_dir: Path, env: dict, rows: list[dict], flush_s: float, started: float):
        self.out_dir, self.env, self.rows, self.flush_s, self.started = out_dir, env, rows, flush_s, started
        self.cost, self.last = 0.0, time.monotonic()

    def flush(self) -> None:
        t0 = time.monotonic()
        write_results(to_frame(self.rows), self.out_dir)
        record_elapsed(self.env, time.monotonic() - self.started)
        write_json(self.out_dir / "environment.json", self.env)
        self.cost = time.monotonic() - t0
        self.last = time.monotonic()

    def flush_if_due(self) -> None:
        if time.monotonic() - self.last > max(self.flush_s, FLUSH_COST_FACTOR * self.cost):
            self.flush()


class _InFlight:
    """:data:`INFLIGHT` in the run directory: the key and name of the configuration this process
    runs, each write atomic (a few hundred bytes: microseconds, against the milliseconds a
    configuration takes at least)."""

    def __init__(self, out_dir: Path, limit_s: float | None):
        self.path, self.key, self.limit_s = out_dir / INFLIGHT, None, float(limit_s or 0.0)

    def start(self, cfg: Config, what: str) -> None:
        self.key = list(map(str, cfg.key))
        write_json(self.path, {"key": self.key, "what": what, "pid": os.getpid(), "started": time.time(),
                               "limit_s": self.limit_s})

    def end(self, cfg: Config) -> None:
        if self.key == list(map(str, cfg.key)):
            self.clear()

    def clear(self) -> None:
        self.key = None
        self.path.unlink(missing_ok=True)


def crashed_rows(out_dir: Path, run_id: str, cfgs: list[Config], done: set, backends: dict) -> list[dict]:
    """The failed row of the configuration a killed session left in :data:`INFLIGHT` (none if
    there is no such note, it is torn, or it names a configuration the run has rows for or no
    longer plans), and the note removed: that configuration killed its process (or hung in native
    code and was killed: a Timeout row), and running it again would do so again."""
    path = out_dir / INFLIGHT
    note = read_note(path)
    path.unlink(missing_ok=True)
    key = tuple(map(str, note["key"])) if note and isinstance(note.get("key"), list) else ()  # else torn
    cfg = next((c for c in cfgs if tuple(map(str, c.key)) == key), None) if key not in done else None
    if cfg is None:
        return []
    if "hung_s" in note:  # killed by a watchdog (bench.run.supervise.overdue)
        return failed_rows(run_id, cfg, backends, hung_reason(float(note.get("limit_s") or 0.0), float(note["hung_s"])))
    return failed_rows(run_id, cfg, backends,
                       f"{CRASHED}: the process running this configuration died inside it (pid {note.get('pid')}: a "
                       "segfault, an abort or an exit in the backend or its libraries); it is not run again. Run it "
                       "alone (--case, --backend, --method) to see the crash")


def _finish_env(env: dict, cf_samples: dict, rounds: int, interrupted: str, n_over: int, n_total: int,
                budget_s: float | None) -> None:
    """The closed-form units, the rounds, and whether the run is complete (and if not, why)."""
    for cid, ts in cf_samples.items():
        env[f"closed_form_s.{cid}"] = repr(float(np.median(ts)))
    env["rounds"] = str(rounds)
    if interrupted:
        env["complete"] = "false"
        env["incomplete_reason"] = interrupted
    elif n_over:
        env["complete"] = "false"
        env["incomplete_reason"] = (f"{n_over} of {n_total} configurations not measured: {OVER_BUDGET} "
                                    f"({budget_s or 0:g} s); finish with --resume and a larger --budget (or none)")
    else:
        env["complete"] = "true"
        env.pop("incomplete_reason", None)


def _kept_and_todo(out_dir: Path, run_id: str, cfgs: list[Config], previous, backends: dict, resume: bool):
    """(rows kept, crashed rows among them, configurations to run) of a new or resumed session:
    a resumed one keeps the rows it has and records the configuration a killed session died in
    (:func:`crashed_rows`) as failed."""
    rows, done = kept_rows(previous)
    crashed = crashed_rows(out_dir, run_id, cfgs, done, backends) if resume else []
    done |= {tuple(str(r[k]) for k in CONFIG_KEY) for r in crashed}
    return rows + crashed, crashed, [c for c in cfgs if tuple(map(str, c.key)) not in done]


def _what(cfg: Config, dtype: bool = False) -> str:
    """A configuration as the progress lines name it (with its dtype: as the in-flight note does)."""
    return f"{cfg.case.id} {cfg.backend_id}{f' {cfg.dtype}' if dtype else ''} {cfg.method} {knob_string(cfg.knobs)}"


def _executor(opts: RunOptions, env: dict):
    """``opts.executor``, or one of this process (sharing the plan with a second process where it has one)."""
    if opts.executor is not None:
        return opts.executor
    if opts.share is not None and opts.rounds == 1:
        return SharingExecutor(environment.machine_key(env), *opts.share)
    return InProcessExecutor(environment.machine_key(env))


def run(suite: Suite, backends: dict[str, Any], out_dir: Path, options: RunOptions | None = None, *,
        progress: Callable[..., None] | None = None, **option_values) -> Any:
    """Run the plan, writing ``results.*`` and ``environment.json`` to ``out_dir``; returns the frame.

    ``options`` (or its fields as keywords): :class:`RunOptions`.  ``progress(done, total, what,
    counts)``: called as each configuration starts (where the executor says) and ends, and at
    the end, ``counts`` the configurations so far by outcome (``ok``, ``skipped``, ``failed``;
    those kept from a resumed session included in ``done``).  ``elapsed_s`` in environment.json
    is the sum over the run's sessions (``elapsed_sessions_s``), kept up to date at every write so
    a killed session's time is not lost.  Each row records ``machine_key`` and ``task_s`` (the
    configuration's wall seconds on its process).  A Ctrl-C stops it; a KeyboardInterrupt that a
    plug-in or a user's field raises by itself is a failed row (:mod:`bench.run.interrupts`).
    """
    with interrupts.watching():
        return _run(suite, backends, out_dir, options, progress, option_values)


def _run(suite, backends, out_dir, options, progress, option_values):
    opts = options if options is not None else RunOptions(**option_values)
    opts.check()
    if opts.policy.accuracy_only:  # nothing timed: each backend's compile-light driver settings, if it has any
        backends = {bid: environment.untimed_backend(b) for bid, b in backends.items()}
    out_dir, started = Path(out_dir), time.monotonic()
    env, previous = _environment(suite, backends, out_dir, opts)
    run_id = env["run_id"]
    died = planning_deaths(out_dir, env) if opts.resume else {}  # (their fields are not run again)
    if died or not opts.resume:
        # before planning: a field ending the process there leaves a run to resume, and the record
        # of those that did (another such field may end this session too)
        write_json(out_dir / "environment.json", env)
    with planning_in(out_dir, died):
        cfgs = plan(suite, list(backends), opts.case_pattern, opts.methods, opts.dtypes,
                    reference_disk=opts.reference_cache_dir, reference_timeout_s=opts.reference_timeout_s)
    if previous is not None:  # before the first write: a refused resume leaves the run as it was
        previous = check_case_versions(previous, cfgs, opts.rerun_cases)
    write_json(out_dir / "environment.json", env)
    if not cfgs:
        raise ValueError(f"nothing to run: no case matches {opts.case_pattern or suite.case_pattern!r} "
                         f"(tags {list(suite.case_tags)}) or no method matches --method; "
                         "`python -m bench cases` lists the cases")
    rows, crashed, todo = _kept_and_todo(out_dir, run_id, cfgs, previous, backends, opts.resume)
    counts = outcome_counts(rows)
    n_before = sum(counts.values())
    n_total = len(todo) + n_before
    executor = _executor(opts, env)
    ref_options = ReferenceOptions(expensive=suite.expensive_references, timeout_s=opts.reference_timeout_s,
                                   disk=opts.reference_cache_dir)
    writer = _Writer(out_dir, env, rows, opts.flush_s, started)
    if crashed:  # written before anything runs: a second crash must not lose it
        writer.flush()
    kept, finished, n_over, interrupted = len(rows), [], 0, ""
    if progress:
        progress(n_before, n_total, "submitting", dict(counts))

    inflight = _InFlight(out_dir, opts.policy.timeout_s)

    def on_start(j: int) -> None:
        cfg = todo[j]
        inflight.start(cfg, _what(cfg, dtype=True))
        if progress:
            progress(n_before + j, n_total, _what(cfg), dict(counts))

    deadline = None if opts.budget_s is None else time.time() + opts.budget_s - (time.monotonic() - started)
    try:
        for j, got, over in executor.execute(run_id, todo, backends, opts.policy, ref_options, opts.budget_s,
                                             deadline, on_start=on_start):
            inflight.end(todo[j])
            finished.append((j, got))
            rows.extend(got)
            counts[outcome_of(got)] += 1
            n_over += over
            if progress:
                progress(n_before + len(finished), n_total, f"last: {_what(todo[j])}", dict(counts))
            writer.flush_if_due()
    except Interrupted as exc:
        interrupted = f"{exc}; {len(todo) - len(finished)} configurations not run: finish with --resume"
    finally:  # only a process that died inside a configuration leaves the note
        inflight.clear()
    # plan order, as the plan lists them (an executor's completion order may differ)
    rows[kept:] = [r for _, got in sorted(finished, key=lambda jg: jg[0]) for r in got]
    if opts.rounds > 1 and not opts.policy.accuracy_only and not interrupted:
        writer.flush()  # the first round's rows on disk before any later round can end the process
        try:
            executor.retime_rounds(rows, todo, opts.rounds, run_id, opts.policy, progress, dict(counts),
                                   inflight=inflight)
        finally:
            inflight.clear()
        write_results(to_frame(rows), out_dir)
    env.update(executor.env_record(env))
    if progress:
        progress(n_total, n_total, "done", dict(counts))
    _finish_env(env, executor.closed_form_samples(), opts.rounds, interrupted, n_over, n_total, opts.budget_s)
    df = to_frame(rows)
    write_results(df, out_dir)
    record_elapsed(env, time.monotonic() - started)
    write_json(out_dir / "environment.json", env)
    return df
