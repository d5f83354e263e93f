"""One configuration, measured: why it does not apply (:func:`skip_reason`), prepare and time
it, check what it returned, judge it against the reference (:func:`run_one`), under the run's
budget (:func:`run_budgeted`), and the extra timing rounds of ``--rounds`` (:func:`retime`,
:func:`pool`).  The same wherever it runs: this process or a dask worker."""

from __future__ import annotations

import copy
import dataclasses
import inspect
import json
import math
import time
import traceback
from typing import Any, Callable

import numpy as np

from impls import METHODS, Unavailable, get_method
from impls.protocol import Declined, declined_reason
from reference import Case
from reference.cases import freeze_arrays
from reference.quadric import ray_sphere_roots

from . import environment, interrupts, references
from .contract import (BackendFault, answers_differ, backend_call, backend_dtypes, backend_methods, check_result,
                       compile_seconds, library_state_kept, owned, result_arrays, status_counts)
from .metrics import measure_accuracy, primary_quantity
from .plan import Config, applies
from .results import OVER_BUDGET, SCHEMA_VERSION, knob_string
from .timing import Timeout, TimingPolicy, measure, time_limit

def closed_form_time(case: Case, policy: TimingPolicy) -> float:
    """Median time of the exact closed-form ray–sphere intersection of ``case.n_rays`` rays in
    numpy float64 (:func:`reference.quadric.ray_sphere_roots`, unit sphere at the origin, whatever
    the case's scene): the run's unit of time, measured with the same policy as the methods."""
    pol = dataclasses.replace(policy, accuracy_only=False)
    timing, _ = measure(closed_form_unit(case), lambda _: None, pol)
    return timing.median_s


def closed_form_unit(case: Case) -> Callable[[], Any]:
    """One call of the run's unit on ``case``'s rays (:func:`closed_form_time`)."""
    o, d = case.origins, case.directions
    return lambda: ray_sphere_roots(o, d, (0.0, 0.0, 0.0), 1.0)


def _device(cfg: Config, backend: Any) -> str:
    try:
        return str(getattr(backend, "device", None) or cfg.backend_id.partition(":")[2] or "cpu")
    except Exception:  # a property that raises: the id's device part stands in
        return cfg.backend_id.partition(":")[2] or "cpu"


def base_row(run_id: str, cfg: Config, backend: Any) -> dict:
    spec = METHODS.get(cfg.method)
    return {
        "schema_version": SCHEMA_VERSION, "run_id": run_id, "case_id": cfg.case.id, "case_version": cfg.case.version,
        "backend": cfg.backend_id, "device": _device(cfg, backend), "dtype": cfg.dtype, "method": cfg.method,
        "family": spec.family if spec else "", "knob": knob_string(cfg.knobs),
        "knobs_json": json.dumps(cfg.knobs, sort_keys=True), "driver_json": environment.driver_record(backend),
        "n_rays": cfg.case.n_rays,
        "quantity": primary_quantity(spec) if spec else "",
    }


def failed_rows(run_id: str, cfg: Config, backends: dict, reason: str) -> list[dict]:
    """The one row of a configuration that failed without running to the end (its process or
    worker died or hung), with ``reason``."""
    return [{**base_row(run_id, cfg, backends.get(cfg.backend_id)), "outcome": "failed", "reason": reason}]


def skip_reason(cfg: Config, backend: Any, limit_s: float | None = None) -> str | None:
    """Why ``cfg`` does not apply, or None.  Checked in the order a reader needs it, the backend's
    optional ``declines(method, scene)`` hook last (:func:`impls.protocol.declined_reason`).  A
    backend whose ``methods()``, ``capabilities`` or ``declines`` break raises :class:`BackendFault`."""
    if isinstance(backend, Unavailable):
        return f"backend unavailable: {backend.reason}"
    if cfg.method not in backend_methods(backend):
        spec = METHODS.get(cfg.method)
        # a method no array library runs (MethodSpec.libs == ()): say who offers it
        why = " (an engine's own query: only engine backends offer it)" if spec is not None and spec.libs == () else ""
        return f"{cfg.backend_id} does not implement {cfg.method}{why}"
    if cfg.dtype not in backend_dtypes(backend):
        return f"{cfg.backend_id} does not support {cfg.dtype}"
    reason = applies(get_method(cfg.method), cfg.case, limit_s)  # (limit_s: a user case's reference)
    if reason:
        return reason
    declined = backend_call(backend, "backend.declines(method, scene)",
                             lambda: declined_reason(backend, cfg.method, cfg.case.scene))
    return f"{cfg.backend_id} declines {cfg.method} on this scene: {declined}" if declined else None


def takes_one_argument(fn: Callable) -> bool:
    """Whether ``fn(x)`` binds (a callable whose signature cannot be read is given the benefit of
    the doubt: the call itself then says)."""
    try:
        inspect.signature(fn).bind(None)
    except TypeError:
        return False
    except ValueError:  # no signature (some builtins)
        return True
    return True


def warmup_policy(backend: Any, policy: TimingPolicy, compile_s: float | None = None) -> TimingPolicy:
    """``policy`` for ``backend``: its ``warmup`` calls only for a backend that compiles
    (``capabilities.jit``; one that does not say, or whose capabilities break, counts as one).
    ``compile_s``: the prepared kernel's ``Prepared.compile_s``.  Where it is None the kernel
    may compile inside its first call (a lazy JIT, which may go on warming up in the calls after
    it), so a long first call does not stand in for the warm-up (``warm_after_s`` = ∞); where
    the compile was reported apart, a first call of at least ``warm_after_s`` does
    (:func:`bench.run.timing.measure`).

    Why: the warm-up call absorbs what a compiling backend does on a kernel's second call
    (numba's dispatch, Warp's module load, XLA's first-run allocations).  A backend that does not
    compile (numpy, torch eager, the engines) pays its one-time costs (allocator growth, lazy
    imports, caches) in the first call, which is timed alone and reported as ``first_call_s``;
    after it the calibration call is already warm and is the first timing sample (a first call
    long enough that the repeat count bounds the samples is the first sample itself:
    :func:`bench.run.timing.measure`).  The samples
    stay honest: at least ``min_repeats`` of them, their median and interquartile range reported,
    so a sample still warming up would show as spread, not hide in the median."""
    try:
        compiles = bool(getattr(backend.capabilities, "jit", True))
    except Exception:  # noqa: BLE001 - a plug-in's broken capabilities: keep the warm-up
        compiles = True
    if not compiles and policy.warmup:
        return dataclasses.replace(policy, warmup=0)
    if compiles and compile_s is None and policy.warm_after_s != math.inf:
        return dataclasses.replace(policy, warm_after_s=math.inf)
    return policy


def own_copy(backend: Any, obj: Any) -> Any:
    """``obj`` (a case's scene or colour field) as ``backend`` gets it: a plug-in's own deep copy,
    so that one that changes what it is given (rebinds a user field's ``fn``, sets a node's
    ``lipschitz``) changes its own configuration, not the scene every later row of every backend
    runs on and is measured against (the 2026-11-30 probe: a plug-in that swapped ``fn`` in its
    ``prepare`` gave every numpy row 68 false hits, blamed on numpy).  The package's own backends
    (``impls.*``) get the object itself: their compiled kernels are kept per scene.  A copy of a
    catalog scene costs at most 0.3 ms (the neural ones; derived caches such as a mesh's AABB tree
    are left out and built again: :meth:`reference.scene.Field.__deepcopy__`)."""
    if type(backend).__module__.partition(".")[0] == "impls":
        return obj
    mine = copy.deepcopy(obj)
    # read-only as the case's own arrays are: a write into them is the plug-in's error to see, not
    # a silent change of its copy
    freeze_arrays(mine, set())
    return mine


def _prepare_and_time(cfg: Config, backend: Any, policy: TimingPolicy):
    """Bind the method to the case (methods that evaluate at given hits get ``t_hit`` = the exact
    depths, isolating their error from root finding) and time it: (prepared, timing, output).
    What ``prepare`` returns must have callables ``run`` and ``result`` (else BackendFault)."""
    case, spec = cfg.case, get_method(cfg.method)
    # the backend gets copies of the rays and depths: one that writes into its inputs (a plug-in's
    # in-place bug) changes its own configuration's rays, not the case that every later row, of
    # every backend, is run on and measured against
    extra = {"t_hit": np.array(case.exact_t)} if spec.needs_t_hit else {}
    if getattr(spec, "needs_color", False):
        # the renderer shades with the very colour field the reference integrates
        extra["color"] = own_copy(backend, references.color_field(case))
    scene = own_copy(backend, case.scene)
    prep = backend_call(backend, f"backend.prepare({cfg.method!r}, …)", lambda: backend.prepare(
        cfg.method, scene, np.array(case.origins), np.array(case.directions), dtype=cfg.dtype,
        t_min=case.t_min, t_max=case.t_max, **extra, **cfg.knobs))
    for name in ("run", "result"):
        if not callable(getattr(prep, name, None)):
            raise BackendFault(f"backend.prepare returned {type(prep).__name__}, which has no callable {name!r} "
                               "(return impls.protocol.Prepared(run=…, result=…))")
    sync = getattr(backend, "synchronize", None)
    if not callable(sync):
        raise BackendFault("the backend has no callable synchronize(out)")
    if not takes_one_argument(sync):
        raise BackendFault("backend.synchronize must take the output of Prepared.run(): synchronize(out) "
                           "(docs/backends.md); it cannot be called with one argument")
    timing, out = measure(lambda: backend_call(backend, "Prepared.run()", prep.run),
                          lambda o: backend_call(backend, "backend.synchronize(out)", lambda: sync(o)),
                          warmup_policy(backend, policy, compile_seconds(prep)), unit=closed_form_unit(case))
    return prep, timing, out


def run_one(run_id: str, cfg: Config, backend: Any, policy: TimingPolicy, cf_time: float,
            cache: dict | None = None, limit: tuple[float, str] | None = None) -> list[dict]:
    """:func:`_run_one`, and afterwards the process-wide library settings as they were before it
    (:func:`bench.run.contract.library_state_kept`): a backend's change of them is its own
    configuration's, not every later row's."""
    with library_state_kept():
        return _run_one(run_id, cfg, backend, policy, cf_time, cache, limit)


def _run_one(run_id: str, cfg: Config, backend: Any, policy: TimingPolicy, cf_time: float,
             cache: dict | None = None, limit: tuple[float, str] | None = None) -> list[dict]:
    """Rows for one configuration (one per quantity; one row when skipped or failed).  Never
    raises for what the backend does (exceptions, contract breaches, hangs past the limit):
    those are failed rows with the reason.  ``limit``: (seconds, what) bounding the configuration
    instead of ``policy.timeout_s`` (the runner passes the smaller of the timeout and the run's
    budget left)."""
    cache = {} if cache is None else cache
    row = base_row(run_id, cfg, backend)
    seconds, what = limit if limit is not None else (policy.timeout_s, "--timeout")
    try:
        reason = skip_reason(cfg, backend, getattr(cache.get("_options"), "timeout_s", None))
    except BaseException as exc:  # e.g. the reference cannot answer for this case, or methods() broke
        if not interrupts.is_fault(exc):
            raise
        return [{**row, "outcome": "failed", "reason": f"planning: {type(exc).__name__}: {exc}",
                 "traceback": traceback.format_exc(limit=5)}]
    if reason:
        return [{**row, "outcome": "skipped", "reason": reason}]
    case, spec = cfg.case, get_method(cfg.method)
    try:
        with time_limit(seconds, what):
            prep, timing, out = _prepare_and_time(cfg, backend, policy)
            started = time.perf_counter()
            raw = backend_call(backend, "Prepared.result(out)", lambda: prep.result(out))
            # converting the returned arrays runs the backend's code too (an __array__, a lazy
            # device array's queued work): inside the limit, so that it cannot hang the run; the
            # timing samples above are untouched (each timed call synchronised already)
            raw = result_arrays(raw)
            result_s = time.perf_counter() - started
            later = None
            if timing.last_out is not None and timing.last_out is not out:
                # the last timed call's answer, to check below that the calls timed computed the
                # answer the first call's accuracy judges (copied first: its buffers may be reused)
                raw = owned(raw)
                later = result_arrays(backend_call(backend, "Prepared.result(out)",
                                                   lambda: prep.result(timing.last_out)))
            compile_s = compile_seconds(prep)
            compile_cache = getattr(prep, "compile_cache", None)
        res = check_result(raw, case.n_rays, tuple(spec.outputs), scene=case.scene, who=cfg.backend_id,
                           dtype=cfg.dtype, t_range=(case.t_min, case.t_max) if spec.family == "root" else None,
                           evaluates=spec.family == "root" and spec.libs != ())
        differ = answers_differ(raw, later, cfg.dtype) if later is not None else ""
        if differ:
            raise BackendFault(f"the timed calls did not give the answer of the checked (first) call: {differ}; every "
                               "call of Prepared.run() must compute the method's answer anew (docs/backends.md), so "
                               "this row's time and accuracy cannot stand")
        counts = status_counts(res.status)
        quantities = measure_accuracy(spec, res, case, cfg.dtype, cfg.knobs, cache)
    except Timeout as exc:
        return [{**row, "outcome": "failed", "reason": f"Timeout: {exc}",
                 "traceback": traceback.format_exc(limit=5)}]
    except Declined as exc:  # the backend does not run this method on this scene: a skip, with its reason
        return [{**row, "outcome": "skipped", "reason": f"{cfg.backend_id} declines {cfg.method} on this scene: {exc}"}]
    except BaseException as exc:  # a failing configuration becomes a row; the run goes on
        if not interrupts.is_fault(exc):
            raise
        return [{**row, "outcome": "failed", "reason": f"{type(exc).__name__}: {exc}",
                 "traceback": traceback.format_exc(limit=5)}]
    timed = _timed_columns(timing, counts, compile_s, compile_cache, result_s, cf_time, policy)
    rows = []
    for q in quantities:
        if "skip" in q:
            rows.append({**row, **timed, "quantity": q["quantity"], "outcome": "skipped", "reason": q["skip"]})
        else:
            rows.append({**row, **timed, **q, "outcome": "ok", "reason": ""})
    return rows or [{**row, **timed, "outcome": "skipped", "reason": "the method returned nothing that has a reference"}]


def _timed_columns(timing, counts: dict, compile_s, compile_cache, result_s: float, cf_time: float,
                   policy: TimingPolicy) -> dict:
    """The columns of a configuration's rows that its timing gives: status counts, first call,
    compile (``compile_cache``: compiled or reused), the samples' median and spread, and the ratio
    to the unit measured beside them; NaN under ``--accuracy-only``, and a timing note (the ratio
    NaN) where ``Prepared.result()`` did work that the timed calls left out."""
    timed = {
        "status_counts": json.dumps(counts, sort_keys=True),
        "first_call_s": timing.first_call_s,
        "compile_s": compile_s if compile_s is not None else max(timing.first_call_s - timing.median_s, 0.0),
        "compile_cache": compile_cache if compile_cache in ("compiled", "reused") else None,
        "time_median_s": timing.median_s, "time_iqr_s": timing.iqr_s,
        "time_samples_s": json.dumps(timing.samples_s),
        # the unit measured beside the samples (bench.run.timing.measure); the case's own where none was
        "time_ratio_cf": timing.median_s / (timing.unit_s if timing.unit_s else cf_time),
        "n_samples": len(timing.samples_s), "loops": timing.loops,
    }
    if policy.accuracy_only:  # one untimed-quality call: no timing claims, no timing comparison
        timed.update({"compile_s": compile_s, "time_median_s": float("nan"), "time_iqr_s": float("nan"),
                      "time_samples_s": "", "time_ratio_cf": float("nan"), "n_samples": 0})
    elif untimed_work(result_s, timing.median_s):
        # work moved out of run() into result() is not timed: the row's time is no measure of the
        # method (a plug-in doing everything in result() was timed at 0.3 µs and picked at ×0.005)
        timed.update({"time_ratio_cf": float("nan"),
                      "timing_note": f"Prepared.result() took {result_s:.3g} s, {result_s / timing.median_s:.3g}× a "
                                     f"timed run() ({timing.median_s:.3g} s): work done there is not timed "
                                     "(result() should only convert; docs/backends.md), so this time is not "
                                     "comparable; "})
    return timed


#: result() slower than this many timed run() calls, and than RESULT_FLOOR_S, does untimed work
#: (the floor is above what a loaded machine's scheduler takes from one call, ~tens of ms: a
#: conversion preempted once must not cost a row its timing)
RESULT_RATIO = 10.0
RESULT_FLOOR_S = 0.05


def untimed_work(result_s: float, run_s: float) -> bool:
    """Whether ``Prepared.result()`` (untimed: it converts what ``run()`` returned) took more than
    :data:`RESULT_RATIO` timed ``run()`` calls and :data:`RESULT_FLOOR_S`: then part of the method's
    work happens there, outside the samples.  (Measured: the built-in backends' result() takes at
    most a few conversions of the outputs, well under one run.)"""
    return result_s > RESULT_FLOOR_S and result_s > RESULT_RATIO * run_s


def over_budget_message(budget_s: float | None) -> str:
    """The reason of a configuration the run's ``--budget`` left unmeasured (prefix :data:`OVER_BUDGET`)."""
    return f"{OVER_BUDGET} ({budget_s or 0:g} s); finish with --resume and a larger --budget (or none)"


def run_budgeted(run_id: str, cfg: Config, backend: Any, policy: TimingPolicy, cf_time: Callable[[], float],
                 cache: dict, budget_s: float | None, left: float | None) -> tuple[list[dict], bool]:
    """One configuration under the run's budget, the same wherever it runs (this process, or a
    dask worker of :mod:`bench.run.cluster`): ``left`` seconds of ``budget_s`` remain (None: no
    budget).  Returns (rows, over): with no budget left, one skipped :data:`OVER_BUDGET` row; else
    :func:`run_one` limited to the smaller of ``policy.timeout_s`` and ``left``, and a run the
    budget interrupted is such a row too ("interrupted in flight").  ``cf_time()`` gives the
    closed-form unit; it is called only when the configuration runs."""
    over_msg = over_budget_message(budget_s)
    if left is not None and left <= 0:
        return [{**base_row(run_id, cfg, backend), "outcome": "skipped", "reason": over_msg}], True
    cf = cf_time()
    limit = (policy.timeout_s, "--timeout")
    if left is not None and (not policy.timeout_s or left < policy.timeout_s):
        limit = (max(left, 1e-3), f"the run's --budget of {budget_s:g} s")
    got = run_one(run_id, cfg, backend, policy, cf, cache, limit=limit)
    if limit[1] != "--timeout" and any(str(r.get("reason", "")).startswith("Timeout:") for r in got):
        # interrupted by the budget, not by its own limit: not measured, like those after it
        return [{**base_row(run_id, cfg, backend), "outcome": "skipped",
                 "reason": over_msg + " (interrupted in flight)"}], True
    return got, False


def retime(cfg: Config, backend: Any, policy: TimingPolicy) -> list[float] | str:
    """Timing samples of one more round for ``cfg`` (prepared afresh, compile excluded), or the
    error message when this round failed."""
    try:  # (the library settings put back after it, as after the first round: run_one)
        with library_state_kept(), time_limit(policy.timeout_s):
            _, timing, _ = _prepare_and_time(cfg, backend, policy)
        return timing.samples_s
    except BaseException as exc:  # the backend's fault is this round's note, not the run's end
        if not isinstance(exc, Timeout) and not interrupts.is_fault(exc):
            raise
        return f"{type(exc).__name__}: {exc}"


def pool(row: dict, extra: list[float] | str, cf_time: float) -> None:
    """Add one round's samples to a result row and recompute its timing summary."""
    if isinstance(extra, str):
        row["timing_note"] = (row.get("timing_note") or "") + f"a later round failed: {extra}; "
        return
    samples = json.loads(row["time_samples_s"]) + list(extra)
    q1, med, q3 = np.percentile(samples, [25, 50, 75])
    row.update({"time_samples_s": json.dumps(samples), "time_median_s": float(med), "time_iqr_s": float(q3 - q1),
                "time_ratio_cf": float(med) / cf_time, "n_samples": len(samples),
                "rounds": int(row.get("rounds") or 1) + 1})

