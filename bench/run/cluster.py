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
  most one task in flight per worker thread (flow control), and reruns a dead worker's task
  itself, on a free one (:func:`bench.run.cluster_jobs.died_again`), so a worker never holds a
  second task beside the one it times, and its death is charged to that one task alone;
* the closed-form unit is measured on the worker that times the configuration, beside it (once
  per case and worker process);
* every row records the worker's :func:`bench.run.environment.machine_key`, address and pid:
  ``bench compare`` compares timings only between equal keys.

Faults: a worker that dies mid-task is replaced (its nanny restarts it) and the task reruns on a
free worker (:func:`bench.run.cluster_jobs.died_again`); one whose worker died more than its
allowed failures becomes a failed row with that reason, and the run goes on.  A hang is cut by
``--timeout`` as in one process (:func:`bench.run.timing.time_limit` works in a worker's task
thread); one in native code, which it cannot cut, by :func:`bench.run.cluster_jobs.hung_jobs`.

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

import heapq
import json
import os
import time
import uuid
from typing import Any, Iterator

import numpy as np
from distributed import Client, LocalCluster, wait

from .cluster_jobs import (TASK_RESOURCE, _Job, died_again, failure_reason, hung_jobs, local_config, plan_jobs,
                           ready_queues, requeue, retime_rounds, task_resources)
from .cluster_worker import WorkerSetup, _config_with_seeds, _noop, reference_task, thread_env, worker_record
from .configuration import base_row, failed_rows, over_budget_message
from .executor import Interrupted
from .references import ReferenceOptions
from .results import knob_string
from .supervise import hung_reason
from .timing import TimingPolicy

LOCAL = "local:"


class RunInterrupted(Interrupted):
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


# -- the client side -------------------------------------------------------------------------


class ClusterExecutor:
    """Runs a plan's configurations on a dask cluster for :func:`bench.run.runner.run` (its
    ``executor``).  ``local``: start a ``LocalCluster`` of that many single-threaded worker
    processes; ``scheduler``: connect to an existing one (its workers must have isobench and the
    same code; for timed runs each must have one thread, ``dask worker --nthreads 1``).
    ``threads``: library threads per worker; ``allocator``: "tuned" or "default" as ``bench
    run``; ``case_specs``: the ``--cases`` to register on every worker; ``allowed_failures``:
    worker deaths a task may cause before it is a failed row (a ``LocalCluster`` only; None: dask's
    ``distributed.scheduler.allowed-failures``, 3); ``lost_after_s``: how long the
    run waits with no worker at all before it stops incomplete.  Use as a context manager."""

    def __init__(self, *, local: int | None = None, scheduler: str | None = None, threads: int = 1,
                 allocator: str = "tuned", case_specs: tuple[str, ...] = (), allowed_failures: int | None = None,
                 lost_after_s: float = 120.0, accuracy_only: bool = False, calibrate: int = 200,
                 backend_specs: dict[str, str] | None = None):
        if (local is None) == (scheduler is None):
            raise ValueError("ClusterExecutor: give exactly one of local (--cluster local:N) and scheduler (--scheduler)")
        self.local, self.scheduler, self.threads, self.allocator = local, scheduler, threads, allocator
        self.case_specs, self.allowed_failures, self.lost_after_s = tuple(case_specs), allowed_failures, lost_after_s
        self.accuracy_only, self.calibrate = accuracy_only, calibrate
        self.backend_specs = dict(backend_specs or {})  # a plug-in's id → the spec its workers resolve
        self.cluster = self.client = self._config = self._retries = None  # _retries: died_again's (local)
        self._record: dict[str, str] = {}
        self._workers: dict[str, dict] = {}     # address → record (every worker seen)
        self._cf: dict[tuple[str, str], list[float]] = {}   # (worker, case) → closed-form samples
        self._overheads: list[float] = []
        self._ref_s: list[float] = []
        self._critical = 0.0
        self._capacity_at, self._workers_max = (0.0, 1), 0
        self.task_resources: dict[str, float] | None = None  # what each task holds (start: TASK_RESOURCE)

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
            self._retries = int(dask.config.get("distributed.scheduler.allowed-failures")
                                if self.allowed_failures is None else self.allowed_failures)
            self._config = dask.config.set(local_config())  # until close()
            self.cluster = LocalCluster(n_workers=self.local, threads_per_worker=1, processes=True,
                                        dashboard_address=None, memory_limit=0,
                                        env=thread_env(self.threads), resources={TASK_RESOURCE: 1})
            self.client = Client(self.cluster)
            where = f"local:{self.local}"
        else:
            try:
                self.client = Client(self.scheduler, timeout=30)
            except (OSError, TimeoutError) as exc:
                raise ValueError(f"--scheduler: cannot reach {self.scheduler} ({type(exc).__name__}: {exc}); is a "
                                 "dask scheduler running there?") from None
            where = f"scheduler {self.scheduler}"
        self.client.register_plugin(WorkerSetup(self.threads, self.allocator, self.case_specs, self.backend_specs))
        if self.scheduler is not None:
            self.client.wait_for_workers(1, timeout=60)
        self.task_resources = task_resources(self.client)
        records = self.client.run(worker_record)
        self._check_workers(records)
        for r in records.values():
            self._workers[r["address"]] = r
        self._record.update({
            "cluster": where, "cluster.start_s": f"{time.perf_counter() - t0:.2f}",
            "cluster.allowed_failures": str(dask.config.get("distributed.scheduler.allowed-failures")
                                            if self._retries is None else self._retries),
            "cluster.threads_per_worker_library": str(self.threads),
            "cluster.task_resource": TASK_RESOURCE if self.task_resources else "none (a worker lacks it)",
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
        if self._config is not None:
            self._config.__exit__(None, None, None)
            self._config = None

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
        """Threads of the running workers (a restarted one registers before it runs), asked ≤ 2×/s."""
        now = time.monotonic()
        if fresh or now - self._capacity_at[0] > 0.5:
            workers = self.client.scheduler_info()["workers"].values()
            self._capacity_at = (now, sum(w["nthreads"] for w in workers if w.get("status", "running") == "running"))
            self._workers_max = max(self._workers_max, len(workers))
        return self._capacity_at[1]

    # -- the plan

    def execute(self, run_id: str, todo: list, backends: dict, policy: TimingPolicy, ref_options: ReferenceOptions,
                budget_s: float | None, deadline: float | None, on_start=None) -> Iterator[tuple[int, list[dict], bool]]:
        """Yield ``(index in todo, rows, over budget)`` for every configuration of ``todo``, in
        the order they finish (module docstring; :meth:`bench.run.executor.Executor.execute`).
        ``on_start`` is not called: a task starts on a worker, unseen by the client."""
        t_start = time.perf_counter()
        self._overheads, self._ref_s, self._cf, self._critical = [], [], {}, 0.0  # per run (main plan, stability)
        self._t_exec = time.time()
        refs, jobs = plan_jobs(run_id, todo, backends, policy, ref_options, budget_s, deadline)
        waiting, ready_refs, ready = ready_queues(refs, jobs)
        inflight: dict[Any, _Job] = {}
        no_worker_since = None
        while ready_refs or ready or inflight:
            capacity = self._capacity()
            while len(inflight) < max(capacity, 1) and (ready_refs or ready):
                if deadline is not None and time.time() >= deadline and ready:
                    _, _, job = heapq.heappop(ready)  # past the budget: no task needed to say so
                    cfg = todo[job.index]
                    yield job.index, [{**base_row(run_id, cfg, backends[cfg.backend_id]), "outcome": "skipped",
                                       "reason": over_budget_message(budget_s)}], True
                    continue
                job = ready_refs.popleft() if ready_refs else heapq.heappop(ready)[2]
                inflight[self._submit(job)] = job
            if not inflight:
                break
            try:
                done = wait(list(inflight), timeout=5.0, return_when="FIRST_COMPLETED").done
            except TimeoutError:
                done = set()
            for job, hung_s in hung_jobs(self.client, inflight, policy):  # native code that never returns
                yield job.index, failed_rows(run_id, todo[job.index], backends,
                                             hung_reason(float(policy.timeout_s), hung_s)), False
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
                if died_again(job, future, self._retries):  # to a free worker thread, as any task
                    requeue(job, future, ready_refs, ready)
                    self._capacity(fresh=True)  # (the dead worker's thread is gone: none submitted to it)
                    continue
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
                                        pure=False, priority=10, resources=self.task_resources)
        else:
            *head, keep_s = job.args
            ref = job.deps[0] if job.deps else None
            seeds = ref.result if ref is not None and ref.result is not None else None
            future = self.client.submit(_config_with_seeds, *head, seeds, keep_s, job.ref_key,
                                        key=f"isobench-config-{uuid.uuid4().hex}", pure=False,
                                        resources=self.task_resources)
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
            job.error = failure_reason(future, job)

    def _config_done(self, run_id: str, cfg, backends: dict, job: _Job, future, now: float):
        if future.status == "finished":
            res = future.result()
            if "error" in res:
                return [{**base_row(run_id, cfg, backends[cfg.backend_id]), "outcome": "failed",
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
        return failed_rows(run_id, cfg, backends, failure_reason(future, job)), False

    def _ref_chain(self, job: _Job) -> list[float]:
        out = []
        r = job.deps[0] if job.deps else None
        while r is not None:
            out.append(r.task_s)
            r = r.deps[0] if r.deps else None
        return out

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
                      progress, counts: dict, inflight=None) -> None:
        """``--rounds``: rounds 2… of every measured configuration, each on the worker that
        measured it first, one task per worker at a time, pooled into its rows with that worker's
        closed-form unit (:func:`bench.run.cluster_jobs.retime_rounds`; ``inflight`` unused)."""
        retime_rounds(self, rows, todo, rounds, run_id, policy, progress, counts)

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


