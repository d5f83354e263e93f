"""The worker side of :mod:`bench.run.cluster`: what a dask worker process runs.

:class:`WorkerSetup` prepares each worker (threads, allocator, the user's cases, its record);
:func:`config_task` measures one configuration with :func:`bench.run.configuration.run_budgeted`,
:func:`reference_task` computes a shared rendering integral, :func:`retime_task` one more timing
round on the worker that measured the configuration first.
"""

from __future__ import annotations

import dataclasses
import os
import socket
import sys
import threading
import time
from pathlib import Path
from typing import Any

from distributed.diagnostics.plugin import WorkerPlugin

from . import environment, references
from .configuration import closed_form_time, retime, run_budgeted
from .plan import Config
from .references import ReferenceOptions
from .timing import TimingPolicy

#: library thread variables a worker's nanny sets before the worker starts (besides THREAD_VARS)
EXTRA_THREAD_VARS = ("NUMBA_NUM_THREADS",)


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
    ``isobench.cases`` entry points), the plug-in backends' specs by id (``backend_specs``), and
    the worker's record (environment, machine key)."""

    name = "isobench-setup"

    def __init__(self, threads: int, allocator: str, case_specs: tuple[str, ...] = (),
                 backend_specs: dict[str, str] | None = None):
        self.threads, self.allocator, self.case_specs = threads, allocator, tuple(case_specs)
        self.backend_specs = dict(backend_specs or {})

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
                       specs=self.backend_specs,
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

        b = _WORKER["backends"][backend_id] = registry.resolve(_WORKER.get("specs", {}).get(backend_id, backend_id))
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
    """One configuration on this worker: :func:`bench.run.configuration.run_budgeted` with the closed-form
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
        cfg = Config(case, backend_id, method, dtype, dict(knobs))
        backend = _backend(backend_id)
        if policy.accuracy_only:  # as the in-process runner: the backend's compile-light driver settings
            backend = environment.untimed_backend(backend)
        cf: dict = {}

        def cf_time() -> float:
            if policy.accuracy_only:
                return float("nan")
            key = (case_id, round_no)
            if key not in _WORKER["cf"]:
                _WORKER["cf"][key] = closed_form_time(case, policy)
            cf["s"] = _WORKER["cf"][key]
            return cf["s"]

        cache = {"_options": _writable(ref_options), **(seeds or {})}
        left = None if deadline is None else deadline - time.time()
        rows, over = run_budgeted(run_id, cfg, backend, policy, cf_time, cache, budget_s, left)
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
        cfg = Config(case, backend_id, method, dtype, dict(knobs))
        key = (case_id, round_no)
        if key not in _WORKER["cf"]:
            _WORKER["cf"][key] = closed_form_time(case, policy)
        return {"samples": retime(cfg, _backend(backend_id), policy), "cf_s": _WORKER["cf"][key], **ident}


def _noop(x):
    return x



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
