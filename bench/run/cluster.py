"""Sweeps on a dask.distributed cluster: ``bench run --cluster local:N`` or ``--scheduler ADDRESS``.

Configurations are tasks (:func:`config_task`, one per configuration); this process — the
client — plans, submits, and is the only writer of the run directory: it receives each
configuration's rows as its task finishes and writes them with the runner's own writer
(:func:`bench.run.runner.run` with a :class:`ClusterExecutor`), so ``--resume``, the files and the
rows are those of a run in one process.  Rows are keyed by configuration: a task that dask
reran (its worker died) gives its rows once, whatever happened before.

Timing stays honest:

* **one configuration per worker at a time**: a ``LocalCluster`` has N worker processes of one
  thread each, their BLAS/OpenMP/torch/XLA/numba threads fixed (``--threads``, default 1) by
  the nanny's environment and a worker plugin (:class:`WorkerSetup`), and the client keeps at
  most one task in flight per worker thread (flow control), so a worker never holds a second
  task beside the one it times — which also means that a worker's death marks as suspect only
  the configuration it was running (dask counts every task a dying worker held);
* the closed-form unit is measured on the worker that times the configuration, beside it (once
  per case and worker process);
* every row records the worker's :func:`bench.run.environment.machine_key`, address and pid:
  ``bench compare`` compares timings only between equal keys.

Faults: a worker that dies mid-task is replaced (its nanny restarts it) and dask reruns the
task elsewhere; a configuration whose worker dies more than
``distributed.scheduler.allowed-failures`` times (:class:`distributed.KilledWorker`) becomes a
failed row with that reason, and the run goes on.  A hang is cut by ``--timeout`` as in one
process (:func:`bench.run.timing.time_limit` works in a worker's task thread).

Shared references: a rendering integral (:func:`bench.run.references.exact_color`) is a task of its
own (:func:`reference_task`), computed once per case × density model × sharpness on some
worker; the configurations that are checked against it are submitted once it is done and
receive its result as a dask dependency (moved between workers by dask, no shared file system
needed); the integrals of one case and model run one after the other, so that one that times
out spares the others as in one process.  The on-disk cache of ``reports/.refcache`` is used as
well where the workers can write it (every worker of a ``LocalCluster`` can), so a later run
reads instead of recomputing.  Why tasks and not only the disk cache: two workers that miss the
same file at once would both compute it, and a remote cluster need not share a file system.
"""

from __future__ import annotations

import dataclasses
import heapq
import json
import os
import socket
import sys
import threading
import time
import uuid
from collections import deque
from pathlib import Path
from typing import Any, Iterator

import numpy as np
from distributed import Client, KilledWorker, LocalCluster, wait
from distributed.diagnostics.plugin import WorkerPlugin

from . import environment, references, runner
from .references import ReferenceOptions
from .results import knob_string
from .timing import TimingPolicy

LOCAL = "local:"
#: library thread variables a worker's nanny sets before the worker starts (besides THREAD_VARS)
EXTRA_THREAD_VARS = ("NUMBA_NUM_THREADS",)


class RunInterrupted(runner.Interrupted):
    """The cluster went away (no worker for ``lost_after_s``, or the scheduler cancelled the
    tasks): the run stops, keeps what it finished, and is marked incomplete (``--resume``)."""


def parse_local(text: str) -> int:
    """N of ``local:N`` (N ≥ 1), else ValueError naming ``--cluster`` and the form."""
    if not isinstance(text, str) or not text.startswith(LOCAL):
        raise ValueError(f"--cluster: expected local:N (N worker processes on this machine), got {text!r}; "
                         "use --scheduler ADDRESS for an existing cluster")
    try:
        n = int(text[len(LOCAL):])
    except ValueError:
        raise ValueError(f"--cluster: N in local:N must be an integer, got {text!r}") from None
    if n < 1:
        raise ValueError(f"--cluster: local:N needs N ≥ 1 worker process, got {n}")
    return n


def thread_env(threads: int) -> dict[str, str]:
    """The library thread variables a worker process starts with: :func:`configure_threads`'s
    (the user's own values win) and numba's."""
    saved = dict(os.environ)
    try:
        environment.configure_threads(threads)
        env = {v: os.environ[v] for v in environment.RECORDED_VARS if os.environ.get(v)}
    finally:
        os.environ.clear()
        os.environ.update(saved)
    for v in EXTRA_THREAD_VARS:
        env[v] = os.environ.get(v) or str(threads)
    return env


# -- the worker side -------------------------------------------------------------------------
#
# State of one worker process, set by WorkerSetup: its record (environment, machine key), the
# backends it resolved and the closed-form units it measured.  Module globals: one process, one
# worker.

_WORKER: dict[str, Any] = {}
_ONE_AT_A_TIME = threading.Lock()  # a configuration is timed alone even on a multi-threaded worker


class WorkerSetup(WorkerPlugin):
    """Prepares every worker, those that replace dead ones included: library threads
    (:func:`bench.run.environment.configure_threads`, numba, torch once imported), the allocator
    (``tuned``: :func:`bench.run.environment.tune_allocator`), the user's cases (``--cases`` and the
    ``isobench.cases`` entry points), and the worker's record (environment, machine key)."""

    name = "isobench-setup"

    def __init__(self, threads: int, allocator: str, case_specs: tuple[str, ...] = ()):
        self.threads, self.allocator, self.case_specs = threads, allocator, tuple(case_specs)

    def setup(self, worker=None):
        environment.configure_threads(self.threads)
        for v in EXTRA_THREAD_VARS:
            os.environ.setdefault(v, str(self.threads))
        if self.allocator == "tuned":
            environment.tune_allocator()
        from reference import user_cases

        user_cases.load_entry_points()
        for spec in self.case_specs:
            try:
                user_cases.load(spec)
            except ValueError:  # already registered (a plugin set up twice in one process)
                pass
        env = environment.collect()
        env["threads"] = str(self.threads)
        env.update({f"env.{v}": os.environ.get(v, "") for v in EXTRA_THREAD_VARS})
        _WORKER.update(env=env, machine_key=environment.machine_key(env), threads=self.threads, backends={}, cf={},
                       address=getattr(worker, "address", ""), pid=os.getpid(), host=socket.gethostname())


def worker_record(dask_worker=None) -> dict:
    """What the client records of a worker (``client.run``): address, host, pid, machine key,
    commit, library versions and thread settings."""
    env = _WORKER.get("env") or {}
    return {"address": getattr(dask_worker, "address", ""), "host": socket.gethostname(), "pid": os.getpid(),
            "nthreads": getattr(dask_worker, "state", None) and dask_worker.state.nthreads,
            "machine_key": _WORKER.get("machine_key", ""), "setup": bool(_WORKER), "commit": env.get("commit", ""),
            "threads": {k[4:]: v for k, v in env.items() if k.startswith("env.") and "THREADS" in k or k == "env.XLA_FLAGS"},
            "versions": {k[8:]: v for k, v in env.items() if k.startswith("version.")}}


def _identity() -> dict:
    if not _WORKER:
        raise RuntimeError("this dask worker was not set up by isobench (WorkerSetup plugin missing)")
    from distributed import get_worker

    try:
        address = get_worker().address
    except ValueError:  # not in a worker (a direct call, in tests)
        address = _WORKER.get("address", "")
    return {"worker": address, "worker_pid": _WORKER["pid"], "machine_key": _WORKER["machine_key"]}


def _backend(backend_id: str):
    """This worker's backend for ``backend_id`` (resolved once per process, its loop driver given
    the run's threads, torch's thread count set once torch is imported)."""
    b = _WORKER["backends"].get(backend_id)
    if b is None:
        from impls import registry

        b = _WORKER["backends"][backend_id] = registry.resolve(backend_id)
        if not isinstance(b, registry.Unavailable):
            environment.configure_driver(b, _WORKER["threads"])
    if "torch" in sys.modules:
        torch = sys.modules["torch"]
        if torch.get_num_threads() != _WORKER["threads"]:
            torch.set_num_threads(_WORKER["threads"])
    return b


def _case(case_id: str, version: str):
    """The worker's case ``case_id``, checked to be the client's (same content hash)."""
    from reference import get_case

    case = get_case(case_id)
    if case.version != version:
        raise ValueError(f"the worker's case {case_id} has version {case.version}, the client's {version}: the worker "
                         "runs other code or data; start the cluster from the same isobench")
    return case


def _writable(opts: ReferenceOptions) -> ReferenceOptions:
    """``opts`` without its disk cache where this worker cannot write it (a remote worker)."""
    if opts.disk is None:
        return opts
    try:
        Path(opts.disk).mkdir(parents=True, exist_ok=True)
        if os.access(opts.disk, os.W_OK):
            return opts
    except OSError:
        pass
    return dataclasses.replace(opts, disk=None)


def config_task(run_id: str, case_id: str, case_version: str, backend_id: str, method: str, dtype: str, knobs: dict,
                policy: TimingPolicy, budget_s: float | None, deadline: float | None, ref_options: ReferenceOptions,
                seeds: dict | None = None, round_no: int = 1) -> dict:
    """One configuration on this worker: :func:`bench.run.runner.run_budgeted` with the closed-form
    unit measured here (once per case and process) and the rendering integrals it needs given in
    ``seeds`` (entries of the reference cache, from :func:`reference_task`).  ``deadline``: the
    run's budget as a wall-clock time (``time.time()``; None: none).  Returns ``{"rows": …,
    "over": bool, "task_s": …, "cf_s": …}`` with the worker's identity on every row, or
    ``{"error": message}`` when the configuration cannot even be set up here (the client then
    writes a failed row)."""
    with _ONE_AT_A_TIME:
        t0 = time.perf_counter()
        ident = _identity()
        try:
            case = _case(case_id, case_version)
        except Exception as exc:  # noqa: BLE001 - a missing or different case is this configuration's failure
            return {"error": f"on worker {ident['worker']}: {type(exc).__name__}: {exc}", **ident}
        cfg = runner.Config(case, backend_id, method, dtype, dict(knobs))
        backend = _backend(backend_id)
        cf: dict = {}

        def cf_time() -> float:
            if policy.accuracy_only:
                return float("nan")
            key = (case_id, round_no)
            if key not in _WORKER["cf"]:
                _WORKER["cf"][key] = runner.closed_form_time(case, policy)
            cf["s"] = _WORKER["cf"][key]
            return cf["s"]

        cache = {"_options": _writable(ref_options), **(seeds or {})}
        left = None if deadline is None else deadline - time.time()
        rows, over = runner.run_budgeted(run_id, cfg, backend, policy, cf_time, cache, budget_s, left)
        task_s = time.perf_counter() - t0
        return {"rows": [{**r, **ident, "task_s": task_s} for r in rows], "over": over, "task_s": task_s,
                "cf_s": cf.get("s"), **ident}


def reference_task(case_id: str, case_version: str, method: str, knobs: dict, ref_options: ReferenceOptions,
                   previous: dict | None = None) -> dict:
    """The rendering integral ``method`` with ``knobs`` is checked against on the case
    (:func:`bench.run.references.exact_color`, on this worker, its disk cache used where writable),
    as entries of the reference cache: the answer (or the :class:`NotApplicable` saying why there
    is none), its seconds, and the "timed out, not attempted again" mark that ``previous`` (the
    same case and model's previous integral) passes along.  An unexpected error is left out, so
    the configurations compute it themselves and fail as in one process."""
    with _ONE_AT_A_TIME:
        t0 = time.perf_counter()
        ident = _identity()
        from impls import get_method

        case = _case(case_id, case_version)
        cache: dict = {"_options": _writable(ref_options)}
        cache.update({k: v for k, v in (previous or {}).get("entries", {}).items() if k[0] == "render_exact_timed_out"})
        try:
            references.exact_color(case, get_method(method), knobs, cache)
        except references.NotApplicable:
            pass
        except Exception as exc:  # noqa: BLE001 - reported by the configurations that need it
            cache.pop(("render_exact", case_id, references.density_model(get_method(method), knobs),
                       float(knobs.get("sharpness", 0) or 0)), None)
            ident["error"] = f"{type(exc).__name__}: {exc}"
        cache.pop("_options")
        return {"entries": cache, "task_s": time.perf_counter() - t0, **ident}


def retime_task(case_id: str, case_version: str, backend_id: str, method: str, dtype: str, knobs: dict,
                policy: TimingPolicy, worker: str, round_no: int) -> dict:
    """One more round of timing samples for a configuration on the worker that measured it
    first (``worker``), with that round's closed-form sample on the same worker; a task that
    lands elsewhere (that worker is gone) returns ``{"moved": …}``: samples from two processes
    are never pooled."""
    with _ONE_AT_A_TIME:
        ident = _identity()
        if ident["worker"] != worker:
            return {"moved": f"its worker {worker} is gone; samples of another process are not pooled", **ident}
        case = _case(case_id, case_version)
        cfg = runner.Config(case, backend_id, method, dtype, dict(knobs))
        key = (case_id, round_no)
        if key not in _WORKER["cf"]:
            _WORKER["cf"][key] = runner.closed_form_time(case, policy)
        return {"samples": runner.retime(cfg, _backend(backend_id), policy), "cf_s": _WORKER["cf"][key], **ident}


def _noop(x):
    return x


# -- the client side -------------------------------------------------------------------------


@dataclasses.dataclass
class _Job:
    kind: str                   # "config" or "reference"
    index: int                  # configuration: its index in the plan's todo list; reference: its number
    args: tuple
    deps: list                  # reference _Jobs this one waits for
    ref_key: tuple | None = None
    submitted: float = 0.0
    result: Any = None          # a reference job's future, once done (kept until the plan is done)
    error: str = ""
    task_s: float = 0.0


class ClusterExecutor:
    """Runs a plan's configurations on a dask cluster for :func:`bench.run.runner.run` (its
    ``executor``).  ``local``: start a ``LocalCluster`` of that many single-threaded worker
    processes; ``scheduler``: connect to an existing one (its workers must have isobench and the
    same code; for timed runs each must have one thread, ``dask worker --nthreads 1``).
    ``threads``: library threads per worker; ``allocator``: "tuned" or "default" as ``bench
    run``; ``case_specs``: the ``--cases`` to register on every worker; ``allowed_failures``:
    worker deaths a configuration may cause before it is a failed row (a ``LocalCluster`` only;
    None: dask's ``distributed.scheduler.allowed-failures``, 3); ``lost_after_s``: how long the
    run waits with no worker at all before it stops incomplete.  Use as a context manager."""

    def __init__(self, *, local: int | None = None, scheduler: str | None = None, threads: int = 1,
                 allocator: str = "tuned", case_specs: tuple[str, ...] = (), allowed_failures: int | None = None,
                 lost_after_s: float = 120.0, accuracy_only: bool = False, calibrate: int = 200):
        if (local is None) == (scheduler is None):
            raise ValueError("ClusterExecutor: give exactly one of local (--cluster local:N) and scheduler (--scheduler)")
        self.local, self.scheduler, self.threads, self.allocator = local, scheduler, threads, allocator
        self.case_specs, self.allowed_failures, self.lost_after_s = tuple(case_specs), allowed_failures, lost_after_s
        self.accuracy_only, self.calibrate = accuracy_only, calibrate
        self.cluster = self.client = None
        self._record: dict[str, str] = {}
        self._workers: dict[str, dict] = {}     # address → record (every worker seen)
        self._cf: dict[tuple[str, str], list[float]] = {}   # (worker, case) → closed-form samples
        self._overheads: list[float] = []
        self._ref_s: list[float] = []
        self._critical = 0.0
        self._capacity_at = (0.0, 1)
        self._workers_max = 0

    # -- life cycle

    def __enter__(self) -> "ClusterExecutor":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def start(self) -> None:
        import dask

        t0 = time.perf_counter()
        if self.local is not None:
            if not self.accuracy_only and self.local * self.threads > (os.cpu_count() or 1):
                raise ValueError(f"--cluster local:{self.local} with --threads {self.threads} needs "
                                 f"{self.local * self.threads} cores, this machine has {os.cpu_count()}: timing needs "
                                 "each worker's cores to itself. Use fewer workers, or --accuracy-only")
            config = {"distributed.nanny.pre-spawn-environ": {},  # not dask's MALLOC_TRIM_THRESHOLD_: see tune_allocator
                      # the statistical profiler samples the task thread's stack every 10 ms under the GIL:
                      # it slowed deep Python code (the rendering integral) several-fold and would bias timings
                      "distributed.worker.profile.enabled": False}
            if self.allowed_failures is not None:
                config["distributed.scheduler.allowed-failures"] = int(self.allowed_failures)
            with dask.config.set(config):
                self.cluster = LocalCluster(n_workers=self.local, threads_per_worker=1, processes=True,
                                            dashboard_address=None, memory_limit=0,
                                            env=thread_env(self.threads))
                self.client = Client(self.cluster)
            where = f"local:{self.local}"
        else:
            try:
                self.client = Client(self.scheduler, timeout=30)
            except (OSError, TimeoutError) as exc:
                raise ValueError(f"--scheduler: cannot reach {self.scheduler} ({type(exc).__name__}: {exc}); is a "
                                 "dask scheduler running there?") from None
            where = f"scheduler {self.scheduler}"
        self.client.register_plugin(WorkerSetup(self.threads, self.allocator, self.case_specs))
        if self.scheduler is not None:
            self.client.wait_for_workers(1, timeout=60)
        records = self.client.run(worker_record)
        self._check_workers(records)
        for r in records.values():
            self._workers[r["address"]] = r
        self._record.update({
            "cluster": where, "cluster.start_s": f"{time.perf_counter() - t0:.2f}",
            "cluster.allowed_failures": str(dask.config.get("distributed.scheduler.allowed-failures")
                                            if self.allowed_failures is None else self.allowed_failures),
            "cluster.threads_per_worker_library": str(self.threads),
            "cluster.dask": f"dask {dask.__version__}, distributed {__import__('distributed').__version__}",
        })
        if self.calibrate:
            self._record["cluster.central_s"] = f"{self._central_cost(self.calibrate):.6f}"

    def close(self) -> None:
        for obj in (self.client, self.cluster):
            if obj is not None:
                try:
                    obj.close()
                except Exception:  # noqa: BLE001 - closing a cluster that is already gone
                    pass
        self.client = self.cluster = None

    def _check_workers(self, records: dict) -> None:
        from .environment import collect

        here = collect()
        bad = [a for a, r in records.items() if not r.get("setup")]
        if bad:
            raise ValueError(f"--scheduler: workers {bad[:3]} did not run isobench's setup; are they started from an "
                             "environment with isobench installed?")
        if not self.accuracy_only:
            multi = [f"{a} ({r['nthreads']} threads)" for a, r in records.items() if (r.get("nthreads") or 1) > 1]
            if multi:
                raise ValueError(f"--scheduler: workers {', '.join(multi[:3])} run several tasks at once: timing needs "
                                 "one configuration per worker at a time. Start workers with `dask worker ADDRESS "
                                 "--nthreads 1` (as many as cores), or pass --accuracy-only")
        commits = {r.get("commit", "unknown") for r in records.values()} - {"unknown"}
        mine = here.get("commit", "unknown")
        if mine != "unknown" and commits and commits != {mine}:
            raise ValueError(f"--scheduler: the workers run isobench commit(s) {sorted(commits)}, this client {mine}: "
                             "results would mix code versions; start the workers from the same checkout")
        versions = {k[8:]: v for k, v in here.items() if k.startswith("version.")}
        for a, r in records.items():
            differ = {lib: (v, r["versions"].get(lib)) for lib, v in versions.items() if r["versions"].get(lib) != v}
            if differ:
                raise ValueError(f"--scheduler: worker {a} has other library versions than this client "
                                 f"(library: (client, worker)) {differ}; install the same constraints.txt on both")

    def _central_cost(self, n: int) -> float:
        """Seconds per task that the scheduler and this client spend centrally: ``n`` empty tasks
        submitted at once, wall time / n (the workers do nothing)."""
        t0 = time.perf_counter()
        futures = self.client.map(_noop, range(n), pure=False)
        wait(futures)
        dt = time.perf_counter() - t0
        del futures
        return dt / n

    def _capacity(self, fresh: bool = False) -> int:
        """Worker threads in the cluster now (asked at most every half second)."""
        now = time.monotonic()
        if fresh or now - self._capacity_at[0] > 0.5:
            nthreads = self.client.nthreads()
            self._capacity_at = (now, sum(nthreads.values()))
            self._workers_max = max(self._workers_max, len(nthreads))
        return self._capacity_at[1]

    # -- the plan

    def execute(self, run_id: str, todo: list, backends: dict, policy: TimingPolicy, ref_options: ReferenceOptions,
                budget_s: float | None, deadline: float | None) -> Iterator[tuple[int, list[dict], bool]]:
        """Yield ``(index in todo, rows, over budget)`` for every configuration of ``todo``, in
        the order they finish (module docstring)."""
        from impls import Unavailable, get_method

        t_start = time.perf_counter()
        self._overheads, self._ref_s, self._cf, self._critical = [], [], {}, 0.0  # per run (main plan, stability)
        self._t_exec = time.time()
        refs: dict[tuple, _Job] = {}
        chains: dict[tuple, _Job] = {}          # (case, model) → its last reference job
        first_user: set[tuple] = set()
        jobs: list[_Job] = []
        for j, cfg in enumerate(todo):
            backend = backends[cfg.backend_id]
            key = None
            if not isinstance(backend, Unavailable):
                try:
                    if runner.skip_reason(cfg, backend) is None:
                        key = references.integral_key(cfg.case, get_method(cfg.method), cfg.knobs, ref_options)
                except Exception:  # noqa: BLE001 - the task itself will record why
                    key = None
            deps = []
            if key is not None:
                if key not in refs:
                    prev = chains.get(key[1:3])
                    refs[key] = _Job("reference", len(refs), (cfg.case.id, cfg.case.version, cfg.method,
                                                              dict(cfg.knobs), ref_options),
                                     [prev] if prev else [], ref_key=key)
                    chains[key[1:3]] = refs[key]
                deps = [refs[key]]
            keep_s = key is not None and key not in first_user  # the first user reports the integral's seconds
            if key is not None:
                first_user.add(key)
            jobs.append(_Job("config", j, (run_id, cfg.case.id, cfg.case.version, cfg.backend_id, cfg.method,
                                           cfg.dtype, dict(cfg.knobs), policy, budget_s, deadline, ref_options,
                                           keep_s), deps, ref_key=key))
        waiting: dict[int, list[_Job]] = {}     # id(reference job) → jobs waiting for it
        ready_refs: deque[_Job] = deque()
        ready: list[tuple[int, int, _Job]] = []  # heap by plan index
        for job in list(refs.values()) + jobs:
            if job.deps:
                waiting.setdefault(id(job.deps[0]), []).append(job)
            elif job.kind == "reference":
                ready_refs.append(job)
            else:
                heapq.heappush(ready, (job.index, id(job), job))
        inflight: dict[Any, _Job] = {}
        no_worker_since = None
        while ready_refs or ready or inflight:
            capacity = self._capacity()
            while len(inflight) < max(capacity, 1) and (ready_refs or ready):
                if deadline is not None and time.time() >= deadline and ready:
                    _, _, job = heapq.heappop(ready)  # past the budget: no task needed to say so
                    cfg = todo[job.index]
                    yield job.index, [{**runner._base_row(run_id, cfg, backends[cfg.backend_id]), "outcome": "skipped",
                                       "reason": runner.over_budget_message(budget_s)}], True
                    continue
                job = ready_refs.popleft() if ready_refs else heapq.heappop(ready)[2]
                inflight[self._submit(job)] = job
            if not inflight:
                break
            try:
                done = wait(list(inflight), timeout=5.0, return_when="FIRST_COMPLETED").done
            except TimeoutError:
                done = set()
            if not done:
                if self._capacity(fresh=True) == 0:
                    no_worker_since = no_worker_since or time.monotonic()
                    if time.monotonic() - no_worker_since > self.lost_after_s:
                        raise RunInterrupted(f"the cluster has had no worker for {self.lost_after_s:g} s")
                else:
                    no_worker_since = None
                continue
            now = time.perf_counter()
            for future in done:
                job = inflight.pop(future)
                if job.kind == "reference":
                    self._reference_done(job, future, now)
                    for nxt in waiting.pop(id(job), []):
                        if nxt.kind == "reference":
                            ready_refs.append(nxt)
                        else:
                            heapq.heappush(ready, (nxt.index, id(nxt), nxt))
                    continue
                cfg = todo[job.index]
                got, over = self._config_done(run_id, cfg, backends, job, future, now)
                future.release()
                yield job.index, got, over
        for r in refs.values():
            r.result = None  # the integrals' futures: dask may forget them now
        self._record["cluster.execute_s"] = f"{time.perf_counter() - t_start:.2f}"

    def _submit(self, job: _Job):
        if job.kind == "reference":
            prev = job.deps[0].result if job.deps else None
            future = self.client.submit(reference_task, *job.args, prev, key=f"isobench-reference-{uuid.uuid4().hex}",
                                        pure=False, priority=10)
        else:
            *head, keep_s = job.args
            ref = job.deps[0] if job.deps else None
            seeds = ref.result if ref is not None and ref.result is not None else None
            future = self.client.submit(_config_with_seeds, *head, seeds, keep_s, job.ref_key,
                                        key=f"isobench-config-{uuid.uuid4().hex}", pure=False)
        job.submitted = time.perf_counter()
        return future

    def _reference_done(self, job: _Job, future, now: float) -> None:
        if future.status == "finished":
            res = future.result()
            job.result = future  # a dependency of the configurations that need it
            job.task_s = float(res.get("task_s", 0.0))
            self._ref_s.append(job.task_s)
            self._seen(res, res.get("task_s", 0.0), now - job.submitted)
        else:
            job.result = None  # the configurations compute it themselves (and fail as in one process)
            job.error = self._failure(future)

    def _config_done(self, run_id: str, cfg, backends: dict, job: _Job, future, now: float):
        if future.status == "finished":
            res = future.result()
            if "error" in res:
                return [{**runner._base_row(run_id, cfg, backends[cfg.backend_id]), "outcome": "failed",
                         "reason": res["error"], "worker": res.get("worker", ""), "worker_pid": res.get("worker_pid"),
                         "machine_key": res.get("machine_key", "")}], False
            self._seen(res, res["task_s"], now - job.submitted)
            if res.get("cf_s") is not None:
                self._cf.setdefault((res["worker"], cfg.case.id), []).append(res["cf_s"])
            chain = sum(self._ref_chain(job)) + res["task_s"]
            self._critical = max(self._critical, chain)
            return res["rows"], bool(res["over"])
        if future.status == "cancelled":
            raise RunInterrupted(f"the scheduler cancelled the task of {cfg.case.id} {cfg.backend_id} {cfg.method} "
                                 f"{knob_string(cfg.knobs)} (scheduler restarted or connection lost)")
        return [{**runner._base_row(run_id, cfg, backends[cfg.backend_id]), "outcome": "failed",
                 "reason": self._failure(future)}], False

    def _ref_chain(self, job: _Job) -> list[float]:
        out = []
        r = job.deps[0] if job.deps else None
        while r is not None:
            out.append(r.task_s)
            r = r.deps[0] if r.deps else None
        return out

    def _failure(self, future) -> str:
        exc = future.exception()
        if isinstance(exc, KilledWorker):
            last = getattr(getattr(exc, "last_worker", None), "address", "?")
            return (f"KilledWorker: its worker process died {exc.allowed_failures + 1} times while running it "
                    f"(distributed.scheduler.allowed-failures = {exc.allowed_failures}; last on {last}): a crash, "
                    "abort or out-of-memory kill in this configuration")
        return f"{type(exc).__name__} (on the cluster): {exc}"

    def _seen(self, res: dict, task_s: float, latency: float) -> None:
        addr = res.get("worker", "")
        if addr and addr not in self._workers:
            self._workers[addr] = {"address": addr, "pid": res.get("worker_pid"), "machine_key": res.get("machine_key")}
        self._overheads.append(max(latency - float(task_s), 0.0))

    def _deaths(self) -> int:
        """Workers that left the cluster unexpectedly (died) since this run's plan started: the
        scheduler's ``remove-worker`` events (a nanny then starts a replacement)."""
        t0 = getattr(self, "_t_exec", None)
        if t0 is None or self.client is None:
            return 0
        try:
            events = self.client.get_events("all")
        except Exception:  # noqa: BLE001 - a count in the record, not a reason to fail the run
            return 0
        return sum(1 for t, m in events if t >= t0 and isinstance(m, dict) and m.get("action") == "remove-worker"
                   and not m.get("expected"))

    def closed_form_samples(self) -> dict[str, list[float]]:
        """Closed-form seconds per case over the workers that measured it (for environment.json;
        each row's ``time_ratio_cf`` uses its own worker's)."""
        out: dict[str, list[float]] = {}
        for (_, cid), ts in self._cf.items():
            out.setdefault(cid, []).extend(ts)
        return out

    def retime_rounds(self, rows: list[dict], todo: list, rounds: int, run_id: str, policy: TimingPolicy,
                      progress, counts: dict) -> None:
        """``--rounds``: rounds 2… of every measured configuration, each on the worker that
        measured it first, one task per worker at a time, pooled into its rows with that worker's
        closed-form unit (:func:`bench.run.runner._pool`)."""
        index: dict[tuple, list[int]] = {}
        where: dict[tuple, str] = {}
        for j, r in enumerate(rows):
            if r.get("outcome") == "ok" and r.get("run_id") == run_id and r.get("worker"):
                k = (r["case_id"], r["backend"], r["dtype"], r["method"], r["knob"])
                index.setdefault(k, []).append(j)
                where[k] = r["worker"]
        todo_ok = [c for c in todo if tuple(map(str, c.key)) in index]
        for rnd in range(2, rounds + 1):
            queues: dict[str, deque] = {}
            for cfg in todo_ok:
                queues.setdefault(where[tuple(map(str, cfg.key))], deque()).append(cfg)
            inflight: dict[Any, tuple[str, Any]] = {}
            n = 0
            while any(queues.values()) or inflight:
                busy = {w for w, _ in inflight.values()}
                for w, q in queues.items():
                    if q and w not in busy:
                        cfg = q.popleft()
                        f = self.client.submit(retime_task, cfg.case.id, cfg.case.version, cfg.backend_id, cfg.method,
                                               cfg.dtype, dict(cfg.knobs), policy, w, rnd, workers=[w],
                                               allow_other_workers=True, pure=False,
                                               key=f"isobench-retime-{uuid.uuid4().hex}")
                        inflight[f] = (w, cfg)
                done = wait(list(inflight), return_when="FIRST_COMPLETED").done
                for f in done:
                    w, cfg = inflight.pop(f)
                    n += 1
                    if progress:
                        progress(n, len(todo_ok), f"round {rnd}/{rounds}: {cfg.case.id} {cfg.backend_id} {cfg.method}",
                                 counts)
                    res = f.result() if f.status == "finished" else {"moved": self._failure(f)}
                    extra = res.get("moved") or res["samples"]
                    if "cf_s" in res and "moved" not in res:
                        self._cf.setdefault((w, cfg.case.id), []).append(res["cf_s"])
                    cf = float(np.median(self._cf.get((w, cfg.case.id), [float("nan")])))
                    for j in index[tuple(map(str, cfg.key))]:
                        runner._pool(rows[j], extra, cf)

    def env_record(self, previous: dict | None = None) -> dict[str, str]:
        """What environment.json records of the cluster (the spread summary reads it);
        ``previous``: the run's environment so far, whose execution seconds and reference tasks a
        resumed session adds to."""
        previous = previous or {}
        o = np.array(self._overheads, float)
        rec = dict(self._record)
        if "cluster.execute_s" in rec and previous.get("cluster.execute_s"):
            rec["cluster.execute_s"] = f"{float(rec['cluster.execute_s']) + float(previous['cluster.execute_s']):.2f}"
        ref_s = json.loads(previous.get("cluster.reference_task_s") or "[]") + [round(x, 4) for x in self._ref_s]
        rec.update({
            "cluster.workers": json.dumps(sorted(self._workers.values(), key=lambda r: str(r.get("address"))),
                                          default=str),
            "cluster.workers_max": str(max(self._workers_max, 1)),
            "cluster.workers_died": str(self._deaths()),
            "cluster.overhead_s": json.dumps({"mean": float(o.mean()), "median": float(np.median(o)),
                                              "p90": float(np.percentile(o, 90)), "n": int(o.size)} if o.size else {}),
            "cluster.reference_task_s": json.dumps(ref_s),
            "cluster.critical_path_s": f"{max(self._critical, float(previous.get('cluster.critical_path_s') or 0)):.3f}",
        })
        return rec


def _config_with_seeds(run_id, case_id, case_version, backend_id, method, dtype, knobs, policy, budget_s, deadline,
                       ref_options, reference, keep_s, ref_key):
    """:func:`config_task` with the seeds taken from its reference task's result (a dask
    dependency, resolved to the value on the worker); ``keep_s``: this configuration is the first
    to use the integral and reports its seconds, as in one process."""
    seeds = None
    if reference is not None:
        seeds = dict(reference.get("entries", {}))
        if not keep_s:
            seeds = {k: v for k, v in seeds.items() if k[0] != "reference_s"}
    return config_task(run_id, case_id, case_version, backend_id, method, dtype, knobs, policy, budget_s, deadline,
                       ref_options, seeds)
