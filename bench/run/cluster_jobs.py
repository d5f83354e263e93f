"""The cluster's bookkeeping, apart from talking to dask: the jobs of a plan (configurations
and the shared reference integrals they wait for, :func:`plan_jobs`), the queues they are
submitted from (:func:`ready_queues`), and the ``--rounds`` re-timing on the worker that measured
each configuration first (:func:`retime_rounds`)."""

from __future__ import annotations

import dataclasses
import heapq
import time
import uuid
from collections import deque
from typing import Any

import numpy as np
from distributed import KilledWorker, wait

from . import references
from .cluster_worker import retime_task
from .configuration import pool, skip_reason
from .references import ReferenceOptions
from .timing import TimingPolicy


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
    deaths: int = 0             # its workers that died while running it (local cluster: died_again)


def plan_jobs(run_id: str, todo: list, backends: dict, policy: TimingPolicy, ref_options: ReferenceOptions,
              budget_s: float | None, deadline: float | None) -> tuple[dict[tuple, _Job], list[_Job]]:
    """(reference jobs by integral key, configuration jobs): a configuration checked against a
    rendering integral waits for that integral's job; the integrals of one case and density
    model form a chain, one after the other (:mod:`bench.run.cluster`)."""
    from impls import Unavailable, get_method

    refs: dict[tuple, _Job] = {}
    chains: dict[tuple, _Job] = {}          # (case, model) → its last reference job
    first_user: set[tuple] = set()
    jobs: list[_Job] = []
    for j, cfg in enumerate(todo):
        backend = backends[cfg.backend_id]
        key = None
        if not isinstance(backend, Unavailable):
            try:
                if skip_reason(cfg, backend) is None:
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
    return refs, jobs


def ready_queues(refs: dict[tuple, _Job], jobs: list[_Job]):
    """(jobs waiting for a reference job, by its id; reference jobs ready; configuration jobs
    ready, a heap by plan index)."""
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
    return waiting, ready_refs, ready


def retime_rounds(executor, rows: list[dict], todo: list, rounds: int, run_id: str, policy: TimingPolicy,
                  progress, counts: dict) -> None:
    """Rounds 2… of every measured configuration on ``executor``'s cluster, each on the worker
    that measured it first, one task per worker at a time, pooled into its rows with that
    worker's closed-form unit (:func:`bench.run.configuration.pool`)."""
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
                    f = executor.client.submit(retime_task, cfg.case.id, cfg.case.version, cfg.backend_id, cfg.method,
                                           cfg.dtype, dict(cfg.knobs), policy, w, rnd, workers=[w],
                                           allow_other_workers=True, pure=False,
                                           resources=getattr(executor, "task_resources", None),
                                           key=f"isobench-retime-{uuid.uuid4().hex}")
                    inflight[f] = (w, cfg)
            done = wait(list(inflight), return_when="FIRST_COMPLETED").done
            for f in done:
                w, cfg = inflight.pop(f)
                n += 1
                if progress:
                    progress(n, len(todo_ok), f"round {rnd}/{rounds}: {cfg.case.id} {cfg.backend_id} {cfg.method}",
                             counts)
                res = f.result() if f.status == "finished" else {"moved": executor._failure(f)}
                extra = res.get("moved") or res["samples"]
                if "cf_s" in res and "moved" not in res:
                    executor._cf.setdefault((w, cfg.case.id), []).append(res["cf_s"])
                cf = float(np.median(executor._cf.get((w, cfg.case.id), [float("nan")])))
                for j in index[tuple(map(str, cfg.key))]:
                    pool(rows[j], extra, cf)


#: the worker resource each task holds, one per worker thread, so that a worker runs one task at a
#: time (a remote worker of several threads too).  The scheduler places by the resources a worker
#: has, not by those in use, so it does not keep a task from waiting on a busy worker:
#: :func:`died_again` does, where it matters (a local cluster's retries)
TASK_RESOURCE = "isobench-task"


def task_resources(client) -> dict[str, float] | None:
    """What each task holds: ``{TASK_RESOURCE: 1}`` where every worker of the cluster declares it (a
    local cluster's do; a remote one's with ``dask worker --resources isobench-task=1``), else None
    (the client's count of tasks in flight alone, which does not place them)."""
    declared = [w.get("resources", {}).get(TASK_RESOURCE, 0) for w in client.scheduler_info()["workers"].values()]
    return {TASK_RESOURCE: 1} if declared and all(v >= 1 for v in declared) else None


def local_config() -> dict[str, Any]:
    """The dask configuration a local cluster runs under, held from its start to its close:

    * ``distributed.nanny.pre-spawn-environ`` empty: not dask's ``MALLOC_TRIM_THRESHOLD_`` (see
      :func:`bench.run.environment.tune_allocator`);
    * the statistical profiler off: it samples the task thread's stack every 10 ms under the GIL,
      slowed deep Python code (the rendering integral) several-fold and would bias timings;
    * ``distributed.deploy.lost-worker-timeout`` a day: a ``LocalCluster`` closes for good a worker
      that has not re-registered 15 s (dask's default) after it died, which is meant for batch jobs
      that are gone; here the worker's nanny is restarting it, and on a loaded machine (CI) that
      took more than 15 s, so the cluster lost the nanny and its restarted worker (a third worker
      death counted, a worker fewer for the rest of the run);
    * ``distributed.scheduler.allowed-failures`` 0: a task whose worker died fails at once, and the
      executor decides whether it runs again (:func:`died_again`).
    """
    return {"distributed.nanny.pre-spawn-environ": {}, "distributed.worker.profile.enabled": False,
            "distributed.deploy.lost-worker-timeout": "24h", "distributed.scheduler.allowed-failures": 0}


def hung_jobs(client, inflight: dict, policy) -> list:
    """``(job, seconds)`` of the configuration tasks in flight (``inflight``: future → job) that
    have run long enough past ``--timeout`` to be hung in native code
    (:func:`bench.run.supervise.hung_for`, counted from their submission: a task is submitted only
    when a worker thread is free for it), each removed from ``inflight``, cancelled and its worker
    restarted (the worker thread cannot be interrupted; its nanny starts a fresh process, and the
    tasks it also ran are run again elsewhere)."""
    from .supervise import hung_for

    out = []
    for future, job in list(inflight.items()):
        if job.kind == "reference":
            continue
        hung_s = hung_for(time.time() - (time.perf_counter() - job.submitted), float(policy.timeout_s or 0.0))
        if hung_s is None:
            continue
        try:
            where = [w for w, keys in client.processing().items() if future.key in keys]
            future.cancel()
            if where:
                client.restart_workers(where, raise_for_error=False)
        except Exception:  # noqa: BLE001 - the row says it hung whether or not the restart worked
            pass
        del inflight[future]
        out.append((job, hung_s))
    return out


def died_again(job: _Job, future, retries: int | None) -> bool:
    """Whether ``job``'s task ended because its worker died and is to run again (a death is
    counted to the job): at most ``retries`` times; None (a remote cluster), never here (its
    scheduler's ``allowed-failures`` retries it).  On a local cluster dask retries nothing
    (:func:`local_config`): it resubmitted a dead worker's task at once to the worker still running
    another, where it waited, and a worker's death is charged to every task sent to it, running or
    waiting (``distributed.scheduler.Scheduler.valid_workers`` places by the resources a worker has,
    not by those in use): a configuration that kills its worker failed a numpy row beside it.  The
    executor resubmits it, like any task, only to a free worker thread."""
    if retries is None or future.status != "error" or not isinstance(future.exception(), KilledWorker):
        return False
    job.deaths += 1
    return job.deaths <= retries


def requeue(job: _Job, future, ready_refs: deque, ready: list) -> None:
    """Put ``job`` back among the ready jobs (:func:`ready_queues`), its failed future released."""
    future.release()
    if job.kind == "reference":
        ready_refs.append(job)
    else:
        heapq.heappush(ready, (job.index, id(job), job))


def failure_reason(future, job: _Job | None = None) -> str:
    """The reason of a configuration whose task failed: its worker died too often
    (:class:`distributed.KilledWorker`; ``job.deaths`` where the executor counted them,
    :func:`died_again`), or the exception it raised on the cluster."""
    exc = future.exception()
    if isinstance(exc, KilledWorker):
        last = getattr(getattr(exc, "last_worker", None), "address", "?")
        if job is not None and job.deaths:
            limit = f"the local cluster's allowed failures = {job.deaths - 1}"
            n = job.deaths
        else:
            limit, n = f"distributed.scheduler.allowed-failures = {exc.allowed_failures}", exc.allowed_failures + 1
        return (f"KilledWorker: its worker process died {n} times while running it ({limit}; last on {last}): a "
                "crash, abort or out-of-memory kill in this configuration")
    return f"{type(exc).__name__} (on the cluster): {exc}"
