"""The runner: plan (cases × methods × dtypes × knobs × backends), measure, record.

Every planned configuration becomes rows, never nothing: ``ok`` (measured; one row per checked
quantity, see :mod:`bench.metrics`), ``skipped`` (with the reason: backend unavailable, method
not implemented, dtype unsupported, scene lacks what the method needs, the backend declines the
scene (``declines`` hook or :class:`impls.protocol.Declined` from ``prepare``), no reference answer) or
``failed`` (the exception, a wrong shape, a silent NaN or a timeout; the run goes on).

Rows are written to disk atomically every ``flush_s`` seconds, or every :data:`FLUSH_COST_FACTOR`
times as long as the last write took once the table is large, so a run that dies keeps what it
finished up to that moment, and ``resume=True`` finishes it: configurations already in the run
directory are kept, the others are run under the same run id.
"""

from __future__ import annotations

import dataclasses
import fnmatch
import datetime as _dt
import json
import secrets
import time
import traceback
from pathlib import Path
from typing import Any, Callable

import numpy as np

from impls import METHODS, Unavailable, get_method
from impls.protocol import Declined, RayResult, Status, declined_reason
from reference import Case, catalog
from reference.quadric import ray_sphere_roots

from . import environment, references
from .metrics import family_skip_reason, finite_rows, measure_accuracy, primary_quantity
from .references import ReferenceOptions
from .results import (OVER_BUDGET, SCHEMA_VERSION, knob_string, read_results, remove_temporaries, to_frame, write_json,
                      write_results)
from .suites import Suite
from .timing import Timeout, TimingPolicy, measure, time_limit

#: columns that identify a configuration (a row is a configuration × quantity)
CONFIG_KEY = ["case_id", "backend", "dtype", "method", "knob"]

#: the results are rewritten whole (parquet and csv, atomically), so a write's cost grows with
#: the run, and writing every ``flush_s`` would take a growing share of a long sweep's wall time
#: (docs/performance.md).  Waiting this many times the last write's cost between writes bounds
#: writing to 1/(1 + FLUSH_COST_FACTOR) of the wall time, at the price of redoing at most that
#: interval's configurations after a kill (--resume).
FLUSH_COST_FACTOR = 10.0


@dataclasses.dataclass(frozen=True)
class Config:
    case: Case
    backend_id: str
    method: str
    dtype: str
    knobs: dict

    @property
    def key(self) -> tuple[str, str, str, str, str]:
        return (self.case.id, self.backend_id, self.dtype, self.method, knob_string(self.knobs))


def new_run_id() -> str:
    return _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%SZ") + "-" + secrets.token_hex(3)


def closed_form_time(case: Case, policy: TimingPolicy) -> float:
    """Median time of the exact closed-form ray–sphere intersection of ``case.n_rays`` rays in
    numpy float64 (:func:`reference.quadric.ray_sphere_roots`, unit sphere at the origin, whatever
    the case's scene): the run's unit of time, measured with the same policy as the methods."""
    o, d = case.origins, case.directions
    pol = dataclasses.replace(policy, accuracy_only=False)
    timing, _ = measure(lambda: ray_sphere_roots(o, d, (0.0, 0.0, 0.0), 1.0), lambda _: None, pol)
    return timing.median_s


class Interrupted(RuntimeError):
    """An executor (:mod:`bench.cluster`) could not finish the plan (its cluster went away): the
    run keeps what finished, is marked incomplete with this message, and ``--resume`` finishes it."""


class BackendFault(ValueError):
    """A backend broke the :class:`impls.protocol.Backend` contract (a wrong type, shape, dtype or
    status code, a missing attribute, a method that raised): its configuration is a failed row
    with this message, and the run goes on."""


def _backend_call(backend: Any, what: str, fn: Callable[[], Any]) -> Any:
    """``fn()`` (a call into user code), any exception turned into a :class:`BackendFault` that
    names ``what`` was called."""
    try:
        return fn()
    except (Timeout, Declined):  # a declined configuration is skipped, not failed (run_one)
        raise
    except (Exception, SystemExit) as exc:  # user code: whatever it raises is its fault, not the run's
        raise BackendFault(f"{what} raised {type(exc).__name__}: {exc}") from exc


def _device(cfg: Config, backend: Any) -> str:
    try:
        return str(getattr(backend, "device", None) or cfg.backend_id.partition(":")[2] or "cpu")
    except Exception:  # a property that raises: the id's device part stands in
        return cfg.backend_id.partition(":")[2] or "cpu"


def _base_row(run_id: str, cfg: Config, backend: Any) -> dict:
    spec = METHODS.get(cfg.method)
    return {
        "schema_version": SCHEMA_VERSION, "run_id": run_id, "case_id": cfg.case.id, "case_version": cfg.case.version,
        "backend": cfg.backend_id, "device": _device(cfg, backend), "dtype": cfg.dtype, "method": cfg.method,
        "family": spec.family if spec else "", "knob": knob_string(cfg.knobs),
        "knobs_json": json.dumps(cfg.knobs, sort_keys=True), "driver_json": environment.driver_record(backend),
        "n_rays": cfg.case.n_rays,
        "quantity": primary_quantity(spec) if spec else "",
    }


def backend_methods(backend: Any) -> tuple[str, ...]:
    """``backend.methods()`` checked: an iterable of method names (else :class:`BackendFault`)."""
    got = _backend_call(backend, "backend.methods()", backend.methods)
    if isinstance(got, str) or not all(isinstance(m, str) for m in _backend_call(backend, "iterating methods()",
                                                                               lambda: list(got))):
        raise BackendFault(f"backend.methods() must return method names (strings), got {got!r:.200}")
    return tuple(got)


def backend_dtypes(backend: Any) -> tuple[str, ...]:
    """``backend.capabilities.dtypes`` checked (else :class:`BackendFault`)."""
    caps = _backend_call(backend, "backend.capabilities", lambda: backend.capabilities)
    dts = _backend_call(backend, "backend.capabilities.dtypes", lambda: caps.dtypes)
    if isinstance(dts, str) or not all(isinstance(d, str) for d in _backend_call(
            backend, "iterating capabilities.dtypes", lambda: list(dts))):
        raise BackendFault(f"backend.capabilities.dtypes must be dtype names (strings), got {dts!r:.200}")
    return tuple(dts)


def skip_reason(cfg: Config, backend: Any) -> str | None:
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
    reason = applies(get_method(cfg.method), cfg.case)
    if reason:
        return reason
    declined = _backend_call(backend, "backend.declines(method, scene)",
                             lambda: declined_reason(backend, cfg.method, cfg.case.scene))
    return f"{cfg.backend_id} declines {cfg.method} on this scene: {declined}" if declined else None


#: the codes a result may hold (IN_PROGRESS is internal to the drivers, never returned)
_STATUS_CODES = frozenset(int(s) for s in Status if s != Status.IN_PROGRESS)


def _array(res: Any, name: str, n: int) -> np.ndarray:
    """``res.<name>`` as a numpy array of shape (n,) with a real numeric dtype (else BackendFault)."""
    if not hasattr(res, name):
        raise BackendFault(f"the result has no {name!r} (a RayResult has t, status, iterations, evals, outputs); "
                           f"got {type(res).__name__}")
    try:
        a = np.asarray(getattr(res, name))
    except Exception as exc:
        raise BackendFault(f"result {name} is not an array: {type(exc).__name__}: {exc}") from exc
    if a.shape != (n,):
        raise BackendFault(f"wrong shape: result {name} has shape {a.shape}, expected ({n},)")
    if a.dtype.kind not in "biuf":
        raise BackendFault(f"result {name} has dtype {a.dtype}, expected a real number dtype")
    return a


def check_result(res: Any, n: int, outputs: tuple[str, ...]) -> RayResult:
    """The per-ray contract, checked on what a backend's ``Prepared.result`` returned, which is
    user code: ``t``, ``status``, ``iterations``, ``evals`` arrays of shape (n,) and real dtype;
    ``status`` integer codes of :class:`impls.protocol.Status`; ``iterations``/``evals`` finite
    and ≥ 0; ``outputs`` a dict holding every declared output with leading dimension n; no silent
    NaN (a non-finite ``t`` or output row on a ray whose status is CONVERGED).  Returns a clean
    :class:`RayResult` of numpy arrays (``t`` float64, counts int64); raises
    :class:`BackendFault` (a ValueError) naming the offending array."""
    t = _array(res, "t", n).astype(np.float64)
    status = _array(res, "status", n)
    if status.dtype.kind == "f":
        if not np.all(np.isfinite(status)) or np.any(status != np.round(status)):
            raise BackendFault(f"result status holds non-integer values (dtype {status.dtype}); status codes are "
                               f"the integers of impls.protocol.Status")
    status = status.astype(np.int64)
    bad = sorted(set(np.unique(status).tolist()) - _STATUS_CODES)
    if bad:
        raise BackendFault(f"result status holds code(s) {bad[:5]} that are not impls.protocol.Status values "
                           f"(IN_PROGRESS is internal); valid: "
                           f"{ {s.name: int(s) for s in Status if s != Status.IN_PROGRESS} }")
    counts = {}
    for name in ("iterations", "evals"):
        a = _array(res, name, n)
        if not np.all(np.isfinite(a)) or np.any(a < 0):
            raise BackendFault(f"result {name} must be finite counts ≥ 0; got min {np.min(a)}, max {np.max(a)}")
        counts[name] = a.astype(np.int64) if a.dtype.kind != "f" else a.astype(np.float64)
    outs = getattr(res, "outputs", None)
    if outs is None:
        outs = {}
    if not isinstance(outs, dict):
        raise BackendFault(f"result outputs must be a dict of arrays, got {type(outs).__name__}")
    conv = status == Status.CONVERGED
    nbad = int(np.sum(conv & ~np.isfinite(t)))
    if nbad:
        raise BackendFault(f"silent NaN: {nbad} rays have non-finite t with status CONVERGED")
    clean = {}
    for name, a in outs.items():
        try:
            clean[name] = np.asarray(a)
        except Exception as exc:
            raise BackendFault(f"output {name} is not an array: {type(exc).__name__}: {exc}") from exc
    for name in outputs:
        if name not in clean:
            raise BackendFault(f"missing output {name!r}; returned {sorted(map(str, clean))}")
        a = clean[name]
        if a.shape[:1] != (n,):
            raise BackendFault(f"wrong shape: output {name} has shape {a.shape}, expected ({n}, …)")
        if a.dtype.kind not in "biufc":
            raise BackendFault(f"output {name} has dtype {a.dtype}, expected numbers")
        nbad = int(np.sum(conv & ~finite_rows(a)))
        if nbad:
            raise BackendFault(f"silent NaN: {nbad} rays have non-finite {name} with status CONVERGED")
    return RayResult(t=t, status=status, iterations=counts["iterations"], evals=counts["evals"], outputs=clean)


def status_counts(status: np.ndarray) -> dict[str, int]:
    """{status name: rays}, computed here from checked codes (a backend's own RayResult subclass
    need not have ``status_counts``, and its answer would be unchecked)."""
    vals, counts = np.unique(status, return_counts=True)
    return {Status(int(v)).name: int(c) for v, c in zip(vals, counts)}


def _prepare_and_time(cfg: Config, backend: Any, policy: TimingPolicy):
    """Bind the method to the case (methods that evaluate at given hits get ``t_hit`` = the exact
    depths, isolating their error from root finding) and time it: (prepared, timing, output).
    What ``prepare`` returns must have callables ``run`` and ``result`` (else BackendFault)."""
    case, spec = cfg.case, get_method(cfg.method)
    extra = {"t_hit": case.exact_t} if spec.needs_t_hit else {}
    if getattr(spec, "needs_color", False):
        # the renderer shades with the very colour field the reference integrates
        extra["color"] = references.color_field(case)
    prep = _backend_call(backend, f"backend.prepare({cfg.method!r}, …)", lambda: backend.prepare(
        cfg.method, case.scene, case.origins, case.directions, dtype=cfg.dtype, t_min=case.t_min,
        t_max=case.t_max, **extra, **cfg.knobs))
    for name in ("run", "result"):
        if not callable(getattr(prep, name, None)):
            raise BackendFault(f"backend.prepare returned {type(prep).__name__}, which has no callable {name!r} "
                               "(return impls.protocol.Prepared(run=…, result=…))")
    sync = getattr(backend, "synchronize", None)
    if not callable(sync):
        raise BackendFault("the backend has no callable synchronize(out)")
    timing, out = measure(lambda: _backend_call(backend, "Prepared.run()", prep.run),
                          lambda o: _backend_call(backend, "backend.synchronize(out)", lambda: sync(o)), policy)
    return prep, timing, out


def _compile_s(prep: Any) -> float | None:
    """``Prepared.compile_s``: a finite number ≥ 0 or None (a missing attribute is None)."""
    v = getattr(prep, "compile_s", None)
    if v is None:
        return None
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise BackendFault(f"Prepared.compile_s must be seconds (a number) or None, got {v!r:.100}") from None
    if not (np.isfinite(f) and f >= 0):
        raise BackendFault(f"Prepared.compile_s must be finite and ≥ 0, got {f}")
    return f


def run_one(run_id: str, cfg: Config, backend: Any, policy: TimingPolicy, cf_time: float,
            cache: dict | None = None, limit: tuple[float, str] | None = None) -> list[dict]:
    """Rows for one configuration (one per quantity; one row when skipped or failed).  Never
    raises for what the backend does (exceptions, contract breaches, hangs past the limit):
    those are failed rows with the reason.  ``limit``: (seconds, what) bounding the configuration
    instead of ``policy.timeout_s`` (the runner passes the smaller of the timeout and the run's
    budget left)."""
    cache = {} if cache is None else cache
    row = _base_row(run_id, cfg, backend)
    seconds, what = limit if limit is not None else (policy.timeout_s, "--timeout")
    try:
        reason = skip_reason(cfg, backend)
    except Exception as exc:  # e.g. the reference cannot answer for this case, or methods() broke
        return [{**row, "outcome": "failed", "reason": f"planning: {type(exc).__name__}: {exc}",
                 "traceback": traceback.format_exc(limit=5)}]
    if reason:
        return [{**row, "outcome": "skipped", "reason": reason}]
    case, spec = cfg.case, get_method(cfg.method)
    try:
        with time_limit(seconds, what):
            prep, timing, out = _prepare_and_time(cfg, backend, policy)
            raw = _backend_call(backend, "Prepared.result(out)", lambda: prep.result(out))
            compile_s = _compile_s(prep)
            compile_cache = getattr(prep, "compile_cache", None)
        res = check_result(raw, case.n_rays, tuple(spec.outputs))
        counts = status_counts(res.status)
        quantities = measure_accuracy(spec, res, case, cfg.dtype, cfg.knobs, cache)
    except Timeout as exc:
        return [{**row, "outcome": "failed", "reason": f"Timeout: {exc}",
                 "traceback": traceback.format_exc(limit=5)}]
    except Declined as exc:  # the backend does not run this method on this scene: a skip, with its reason
        return [{**row, "outcome": "skipped", "reason": f"{cfg.backend_id} declines {cfg.method} on this scene: {exc}"}]
    except (Exception, SystemExit) as exc:  # a failing configuration becomes a row; the run goes on
        return [{**row, "outcome": "failed", "reason": f"{type(exc).__name__}: {exc}",
                 "traceback": traceback.format_exc(limit=5)}]
    timed = {
        "status_counts": json.dumps(counts, sort_keys=True),
        "first_call_s": timing.first_call_s,
        "compile_s": compile_s if compile_s is not None else max(timing.first_call_s - timing.median_s, 0.0),
        "compile_cache": compile_cache if compile_cache in ("compiled", "reused") else None,
        "time_median_s": timing.median_s, "time_iqr_s": timing.iqr_s,
        "time_samples_s": json.dumps(timing.samples_s), "time_ratio_cf": timing.median_s / cf_time,
        "n_samples": len(timing.samples_s), "loops": timing.loops,
    }
    if policy.accuracy_only:  # one untimed-quality call: no timing claims, no timing comparison
        timed.update({"compile_s": compile_s, "time_median_s": float("nan"), "time_iqr_s": float("nan"),
                      "time_samples_s": "", "time_ratio_cf": float("nan"), "n_samples": 0})
    rows = []
    for q in quantities:
        if "skip" in q:
            rows.append({**row, **timed, "quantity": q["quantity"], "outcome": "skipped", "reason": q["skip"]})
        else:
            rows.append({**row, **timed, **q, "outcome": "ok", "reason": ""})
    return rows or [{**row, **timed, "outcome": "skipped", "reason": "the method returned nothing that has a reference"}]


def over_budget_message(budget_s: float | None) -> str:
    """The reason of a configuration the run's ``--budget`` left unmeasured (prefix :data:`OVER_BUDGET`)."""
    return f"{OVER_BUDGET} ({budget_s or 0:g} s); finish with --resume and a larger --budget (or none)"


def run_budgeted(run_id: str, cfg: Config, backend: Any, policy: TimingPolicy, cf_time: Callable[[], float],
                 cache: dict, budget_s: float | None, left: float | None) -> tuple[list[dict], bool]:
    """One configuration under the run's budget, the same wherever it runs (this process, or a
    dask worker of :mod:`bench.cluster`): ``left`` seconds of ``budget_s`` remain (None: no
    budget).  Returns (rows, over): with no budget left, one skipped :data:`OVER_BUDGET` row; else
    :func:`run_one` limited to the smaller of ``policy.timeout_s`` and ``left``, and a run the
    budget interrupted is such a row too ("interrupted in flight").  ``cf_time()`` gives the
    closed-form unit; it is called only when the configuration runs."""
    over_msg = over_budget_message(budget_s)
    if left is not None and left <= 0:
        return [{**_base_row(run_id, cfg, backend), "outcome": "skipped", "reason": over_msg}], True
    cf = cf_time()
    limit = (policy.timeout_s, "--timeout")
    if left is not None and (not policy.timeout_s or left < policy.timeout_s):
        limit = (max(left, 1e-3), f"the run's --budget of {budget_s:g} s")
    got = run_one(run_id, cfg, backend, policy, cf, cache, limit=limit)
    if limit[1] != "--timeout" and any(str(r.get("reason", "")).startswith("Timeout:") for r in got):
        # interrupted by the budget, not by its own limit: not measured, like those after it
        return [{**_base_row(run_id, cfg, backend), "outcome": "skipped",
                 "reason": over_msg + " (interrupted in flight)"}], True
    return got, False


def retime(cfg: Config, backend: Any, policy: TimingPolicy) -> list[float] | str:
    """Timing samples of one more round for ``cfg`` (prepared afresh, compile excluded), or the
    error message when this round failed."""
    try:
        with time_limit(policy.timeout_s):
            _, timing, _ = _prepare_and_time(cfg, backend, policy)
        return timing.samples_s
    except (Exception, SystemExit, Timeout) as exc:
        return f"{type(exc).__name__}: {exc}"


def _pool(row: dict, extra: list[float] | str, cf_time: float) -> None:
    """Add one round's samples to a result row and recompute its timing summary."""
    if isinstance(extra, str):
        row["timing_note"] = (row.get("timing_note") or "") + f"a later round failed: {extra}; "
        return
    samples = json.loads(row["time_samples_s"]) + list(extra)
    q1, med, q3 = np.percentile(samples, [25, 50, 75])
    row.update({"time_samples_s": json.dumps(samples), "time_median_s": float(med), "time_iqr_s": float(q3 - q1),
                "time_ratio_cf": float(med) / cf_time, "n_samples": len(samples),
                "rounds": int(row.get("rounds") or 1) + 1})


def select_cases(suite: Suite, case_pattern: str | None) -> list[Case]:
    """``--case`` globs replace the suite's selection; otherwise the suite's glob and tags."""
    if case_pattern:
        return catalog(case_pattern)
    return catalog(suite.case_pattern, set(suite.case_tags) or None)


def applies(spec, case) -> str | None:
    """Why ``spec`` cannot run on ``case`` whatever the backend (scene requirements, missing
    reference answers), or None."""
    try:
        return spec.skip_reason(case.scene) or family_skip_reason(spec, case)
    except Exception as exc:  # a reference that cannot answer is a reason, not a crash
        return f"planning: {type(exc).__name__}: {exc}"


def plan(suite: Suite, backend_ids: list[str], case_pattern: str | None, methods: list[str] | None,
         dtypes: list[str] | None) -> list[Config]:
    """Configurations in measuring order.

    Per method: the cases it applies to (at most ``suite.max_cases``, all when ``--case`` is
    given; fewest rays first with ``suite.small_cases_first``, one per scene family in turn with
    ``suite.diverse_cases``), its knob sweep on the first ``suite.sweep_cases`` of them and its
    default knobs on the rest (plus, beyond ``max_cases``, every applicable case matching
    the method's ``suite.always_cases``, at default knobs; secondary dtypes: see ``Suite.secondary_dtype_cases``;
    never the suite's ``exclude_cases`` for it, unless ``--case`` names cases other than by the
    match-all ``*``); a case it does not apply to gets one configuration (default knobs), which the
    runner records as skipped with the reason.  Order: every default-knob configuration first
    (so a time budget cuts sweep points, not coverage), then the sweep points; within each,
    case by case, knobs outer and backends inner, rotated by one at every knob, so backends
    interleave in time and none is always first."""
    if methods:
        unknown = [m for m in methods if m not in METHODS]
        if unknown:
            raise ValueError(f"--method: unknown method(s) {unknown}; known: {sorted(METHODS)}")
    names = [m for m in (suite.methods or tuple(METHODS)) if not methods or m in methods]
    for dt in dtypes or ():
        if dt not in ("float64", "float32", "float16", "bfloat16"):
            raise ValueError(f"--dtype: unknown dtype {dt!r}; use float64 and/or float32")
    cases = select_cases(suite, case_pattern)
    explicit = bool(case_pattern)
    # the suite's cost exclusions hold for the match-all sweep, not for cases named on purpose
    names_cases = explicit and any(g.strip() not in ("", "*") for g in str(case_pattern).split(","))
    if suite.small_cases_first and not explicit:
        cases = sorted(cases, key=lambda c: c.n_rays)  # stable: catalog order among equals
    order = {c.id: i for i, c in enumerate(cases)}
    # (stage, case index, case, method, knob index, knobs, rank among the method's applicable cases)
    work: list[tuple[int, int, Case, str, int, dict, int]] = []
    for method in names:
        spec = METHODS[method]
        sweep = suite.sweep_for(spec)
        usable = []
        excluded = () if names_cases else (*suite.exclude_cases.get(spec.family, ()),
                                             *suite.exclude_cases.get(spec.name, ()))
        for case in cases:
            if any(fnmatch.fnmatchcase(case.id, g) for g in excluded):
                continue
            if applies(spec, case) is not None:
                work.append((0, order[case.id], case, method, 0, sweep[0], 0))
            else:
                usable.append(case)
        if suite.diverse_cases and not explicit:
            lead = suite.lead_cases.get(spec.family, suite.lead_cases.get("*", ()))
            usable = _one_per_family(usable, lead, shift=names.index(method) if suite.rotate_families else 0)
        if not explicit and suite.max_cases is not None:
            globs = suite.always_cases.get(spec.name, suite.always_cases.get(spec.family, ()))
            extra = [c for c in usable[suite.max_cases:] if any(fnmatch.fnmatchcase(c.id, g) for g in globs)]
            usable = usable[:suite.max_cases] + extra
        for rank, case in enumerate(usable):
            swept = explicit or suite.sweep_cases is None or rank < suite.sweep_cases
            for k, knobs in enumerate(sweep if swept else sweep[:1]):
                work.append((0 if k == 0 else 1, order[case.id], case, method, k, knobs, rank))
    work.sort(key=lambda w: (w[0], w[1]))  # stable: method order, then knob order, kept
    all_dtypes = list(dtypes or suite.dtypes)
    cfgs = []
    for _, _, case, method, k, knobs, rank in work:
        for i, dtype in enumerate(method_dtypes(METHODS[method], all_dtypes, explicit=bool(dtypes))):
            if i > 0 and not dtypes and suite.secondary_dtype_cases is not None and (
                    k > 0 or rank >= suite.secondary_dtype_cases):
                continue  # secondary dtypes: defaults on the first cases only (see Suite)
            r = k % max(len(backend_ids), 1)
            for bid in backend_ids[r:] + backend_ids[:r]:
                cfgs.append(Config(case, bid, method, dtype, dict(knobs)))
    return cfgs


def method_dtypes(spec, run_dtypes: list[str], explicit: bool) -> list[str]:
    """The dtypes ``spec`` is planned in: the run's, or for a method that computes in its own
    (``MethodSpec.dtypes``, an engine's ``raycast``) those, narrowed to the ones ``--dtype`` names
    (``explicit``) when it names any of them (when it names none, the run's dtypes: the rows are
    skipped with the reason, not left out)."""
    own = getattr(spec, "dtypes", None)
    if not own:
        return list(run_dtypes)
    if explicit:
        return [d for d in run_dtypes if d in own] or list(run_dtypes)
    return list(own)


def _family(case) -> str:
    return case.id.split(".", 1)[0]


def _one_per_family(cases: list, lead: tuple[str, ...] = (), shift: int = 0) -> list:
    """``cases`` reordered: those of ``lead`` in ``cases`` (in that order; the first is where the
    sweep runs), then round-robin over the other scene families (first case of each, then
    second…), the families rotated by ``shift`` so that different methods cover different
    families."""
    first = [c for lid in lead for c in cases if c.id == lid]
    by_family: dict[str, list] = {}
    for c in cases:
        if c not in first:
            by_family.setdefault(_family(c), []).append(c)
    lead_families = {_family(c) for c in first}
    others = [g for f, g in by_family.items() if f not in lead_families]
    k = shift % len(others) if others else 0
    # lead families come last, so the cases after the lead ones are of other families
    groups = others[k:] + others[:k] + [g for f, g in by_family.items() if f in lead_families]
    out, depth = list(first), 0
    while len(out) < len(cases):
        out += [g[depth] for g in groups if depth < len(g)]
        depth += 1
    return out


def check_case_versions(previous, cfgs: list[Config], rerun_cases: list[str] | None = None):
    """The rows of a resumed run that may be kept: every planned case's recorded ``case_version``
    must be its version now (its content hash, :attr:`reference.cases.Case.version`), else the
    finished run would mix rows of two versions of one case (an unseeded user factory, an edited
    module).  A changed case matching a glob of ``rerun_cases`` has its old rows dropped (it runs
    again, whole); any other is a ValueError naming it, both versions and the fix.  Returns
    ``previous`` less the dropped rows."""
    if previous is None or not len(previous) or "case_version" not in previous.columns:
        return previous
    now = {c.case.id: str(c.case.version) for c in cfgs}
    recorded = previous.groupby("case_id")["case_version"].agg(lambda v: sorted(set(map(str, v))))
    changed = {cid: vs for cid, vs in recorded.items() if cid in now and vs != [now[cid]]}
    rerun = {cid for cid in changed if any(fnmatch.fnmatchcase(cid, g) for g in rerun_cases or ())}
    refused = sorted(set(changed) - rerun)
    if refused:
        shown = "; ".join(f"{cid} (recorded version {', '.join(changed[cid])}, now {now[cid]}: "
                          f"{int((previous['case_id'] == cid).sum())} rows)" for cid in refused[:5])
        more = f" and {len(refused) - 5} more" if len(refused) > 5 else ""
        raise ValueError(f"--resume: {len(refused)} case(s) changed since the run started: {shown}{more}; their rows "
                         f"would mix two versions of one case. Pass --rerun-case '{','.join(refused[:5])}' to drop "
                         "their rows and run them again, or start a new run with another --out")
    return previous[~previous["case_id"].isin(rerun)] if rerun else previous


def _done_keys(df) -> set[tuple]:
    if df is None or not len(df):
        return set()
    return set(map(tuple, df[CONFIG_KEY].astype(str).itertuples(index=False, name=None)))


def outcome_of(rows: list[dict]) -> str:
    """A configuration's outcome from its rows: ``ok`` if any quantity was measured, else
    ``failed`` if any failed, else ``skipped`` (as ``bench.report.config_outcomes``)."""
    outs = {r.get("outcome") for r in rows}
    return "ok" if "ok" in outs else "failed" if "failed" in outs else "skipped"


def _versions(bid: str, backend: Any) -> dict[str, str]:
    """``backend.versions()`` as recorded in environment.json; a versions() that raises or
    returns something else is recorded as such (the run goes on)."""
    try:
        got = backend.versions()
        if not isinstance(got, dict):
            raise TypeError(f"returned {type(got).__name__}, expected a dict of library → version")
        return {f"backend.{bid}.{k}": str(v) for k, v in got.items()}
    except (Exception, SystemExit) as exc:
        return {f"backend.{bid}.versions_error": f"{type(exc).__name__}: {exc}"[:300]}


def _elapsed(env: dict, session_s: float) -> None:
    """Record this session's seconds: ``elapsed_sessions_s`` (a JSON list, one entry per session
    of the run: the first and every ``--resume``) and ``elapsed_s``, their sum."""
    sessions = json.loads(env.get("elapsed_sessions_s") or "[]")
    sessions[-1] = round(session_s, 1)
    env["elapsed_sessions_s"] = json.dumps(sessions)
    env["elapsed_s"] = f"{sum(sessions):.1f}"


def run(suite: Suite, backends: dict[str, Any], out_dir: Path, *, case_pattern: str | None = None,
        methods: list[str] | None = None, dtypes: list[str] | None = None, policy: TimingPolicy = TimingPolicy(),
        run_id: str | None = None, progress: Callable[..., None] | None = None,
        resume: bool = False, flush_s: float = 1.0, env_extra: dict | None = None,
        budget_s: float | None = None, rounds: int = 1, reference_cache_dir: Path | None = None,
        reference_timeout_s: float = 30.0, executor: Any = None, rerun_cases: list[str] | None = None) -> "Any":
    """Run the plan, writing ``results.*`` and ``environment.json`` to ``out_dir``; returns the frame.

    ``resume``: ``out_dir`` holds a partial run; its rows are kept, its run id reused, and only
    the configurations it lacks are run (temporary files that killed writers left are removed
    first).  ``budget_s`` (None: none): a wall-clock guard against a hang, not a plan: each
    configuration is limited to the smaller of ``policy.timeout_s`` and the budget left, and
    once it is spent the configuration in flight and those left become ``skipped`` rows whose
    reason starts with :data:`OVER_BUDGET`; environment.json then says ``complete: "false"`` with
    ``incomplete_reason``, and ``bench compare`` refuses to gate on it (``--resume``, with a larger
    budget or none, finishes them: resume re-runs configurations without a measured row).
    ``rounds``: the whole plan is timed ``rounds`` times, round after round, and each
    configuration's samples pooled (:func:`retime`), so slow drift of a shared machine's load
    shows up as spread within a configuration instead of as a difference between runs.
    ``reference_cache_dir``: where costly reference answers are kept across runs (None: not kept);
    ``reference_timeout_s``: limit on one costly reference computation (a rendering integral).
    ``progress(done, total, what, counts)``: called before each configuration and at the end,
    ``counts`` the configurations so far by outcome (``ok``, ``skipped``, ``failed``; those kept
    from a resumed session included in ``done``).
    ``elapsed_s`` in environment.json is the sum over the run's sessions (``elapsed_sessions_s``),
    kept up to date at every flush so a killed session's time is not lost.
    ``executor`` (None: this process, one configuration after the other): runs the configurations
    elsewhere, e.g. :class:`bench.cluster.ClusterExecutor` on a dask cluster; planning, resume,
    the rows kept, the files written and the budget's rules are the same, and this process stays
    the one writer of the run directory.  Each row records ``machine_key`` (and ``task_s``, the
    configuration's wall seconds on its process).
    ``rerun_cases`` (globs on case ids; resume only): cases whose content changed since the run
    started are run again, their old rows dropped; any other changed case refuses the resume
    (:func:`check_case_versions`).
    """
    if rounds < 1:
        raise ValueError(f"--rounds must be ≥ 1, got {rounds}")
    if budget_s is not None and not (budget_s >= 0 and np.isfinite(budget_s)):
        raise ValueError(f"--budget must be a finite number of seconds ≥ 0, got {budget_s}")
    out_dir = Path(out_dir)
    started = time.monotonic()
    previous = None
    if resume:
        if not (out_dir / "environment.json").exists():
            raise ValueError(f"--resume: {out_dir} holds no run to resume (no environment.json); drop --resume")
        remove_temporaries(out_dir)
        try:
            env = json.loads((out_dir / "environment.json").read_text())
            run_id = env["run_id"]
        except (ValueError, KeyError) as exc:
            raise ValueError(f"--resume: {out_dir / 'environment.json'} is not a run's environment "
                             f"({type(exc).__name__}: {exc}); start a new run with another --out") from None
        try:
            previous = read_results(out_dir)
        except FileNotFoundError:
            previous = None
        env["resumed"] = str(int(env.get("resumed", "0")) + 1)
        if "elapsed_sessions_s" not in env:  # a run recorded before sessions were
            env["elapsed_sessions_s"] = json.dumps([float(env["elapsed_s"])] if env.get("elapsed_s") else [])
    else:
        run_id = run_id or new_run_id()
        env = environment.collect()
        env["run_id"] = run_id
        env["elapsed_sessions_s"] = "[]"
    env["elapsed_sessions_s"] = json.dumps(json.loads(env["elapsed_sessions_s"]) + [0.0])
    env["suite"] = suite.name
    env["complete"] = "false"
    env["incomplete_reason"] = "running (or killed): finish it with --resume"
    env["budget_s"] = "none" if budget_s is None else f"{budget_s:g}"
    env["timing_policy"] = json.dumps(dataclasses.asdict(policy), sort_keys=True)
    env.update(env_extra or {})
    for bid, b in backends.items():
        if not isinstance(b, Unavailable):
            env.update(_versions(bid, b))
            if environment.driver_record(b):
                env[f"backend.{bid}.driver"] = environment.driver_record(b)
    cfgs = plan(suite, list(backends), case_pattern, methods, dtypes)
    if previous is not None:  # before the first write: a refused resume leaves the run as it was
        previous = check_case_versions(previous, cfgs, rerun_cases)
    write_json(out_dir / "environment.json", env)
    if not cfgs:
        raise ValueError(f"nothing to run: no case matches {case_pattern or suite.case_pattern!r} "
                         f"(tags {list(suite.case_tags)}) or no method matches --method; "
                         "`python -m bench cases` lists the cases")
    done = _done_keys(previous)
    rows: list[dict] = previous.to_dict("records") if previous is not None else []
    if resume and previous is not None:  # budget-skipped rows are redone
        over = previous["reason"].fillna("").astype(str).str.startswith(OVER_BUDGET)
        rows = [r for r, o in zip(rows, over) if not o]
        done = _done_keys(previous[~over])
    todo = [c for c in cfgs if tuple(map(str, c.key)) not in done]
    counts = {"ok": 0, "skipped": 0, "failed": 0}
    if rows:
        kept: dict[tuple, list[dict]] = {}
        for r in rows:
            kept.setdefault(tuple(str(r[k]) for k in CONFIG_KEY), []).append(r)
        for g in kept.values():
            counts[outcome_of(g)] += 1
    n_total, n_before = len(todo) + sum(counts.values()), sum(counts.values())
    cf_cache: dict[str, float] = {}
    ref_options = ReferenceOptions(expensive=suite.expensive_references, timeout_s=reference_timeout_s,
                                   disk=reference_cache_dir)
    ref_cache: dict = {"_options": ref_options}
    here = environment.machine_key(env)

    flush_cost = 0.0

    def flush():
        nonlocal flush_cost
        t0 = time.monotonic()
        write_results(to_frame(rows), out_dir)
        _elapsed(env, time.monotonic() - started)
        write_json(out_dir / "environment.json", env)
        flush_cost = time.monotonic() - t0
        return time.monotonic()

    def flush_due() -> bool:
        return time.monotonic() - last_write > max(flush_s, FLUSH_COST_FACTOR * flush_cost)

    last_write = time.monotonic()
    n_over = 0
    interrupted = ""

    def cf_time(case: Case) -> float:
        if case.id not in cf_cache and not policy.accuracy_only:
            cf_cache[case.id] = closed_form_time(case, policy)
        return cf_cache.get(case.id, float("nan"))

    if executor is not None:
        kept = len(rows)
        finished: list[tuple[int, list[dict]]] = []  # (index in todo, rows): completion order
        if progress:
            progress(n_before, n_total, "submitting", dict(counts))
        deadline = None if budget_s is None else time.time() + budget_s - (time.monotonic() - started)
        try:
            for j, got, over in executor.execute(run_id, todo, backends, policy, ref_options, budget_s, deadline):
                finished.append((j, got))
                rows.extend(got)
                counts[outcome_of(got)] += 1
                n_over += over
                if progress:
                    cfg = todo[j]
                    progress(n_before + len(finished), n_total, f"last: {cfg.case.id} {cfg.backend_id} {cfg.method} "
                             f"{knob_string(cfg.knobs)}", dict(counts))
                if flush_due():
                    last_write = flush()
        except Interrupted as exc:
            interrupted = f"{exc}; {len(todo) - len(finished)} configurations not run: finish with --resume"
        # plan order, as a run in one process writes them (completion order is the cluster's)
        rows[kept:] = [r for _, got in sorted(finished, key=lambda jg: jg[0]) for r in got]
        cf_samples: dict = executor.closed_form_samples()
        if rounds > 1 and not policy.accuracy_only and not interrupted:
            executor.retime_rounds(rows, todo, rounds, run_id, policy, progress, dict(counts))
            write_results(to_frame(rows), out_dir)
        env.update(executor.env_record(env))
    for i, cfg in enumerate(todo if executor is None else ()):
        if progress:
            progress(n_before + i, n_total, f"{cfg.case.id} {cfg.backend_id} {cfg.method} {knob_string(cfg.knobs)}",
                     dict(counts))
        left = None if budget_s is None else budget_s - (time.monotonic() - started)
        t0 = time.perf_counter()
        got, over = run_budgeted(run_id, cfg, backends[cfg.backend_id], policy, lambda: cf_time(cfg.case), ref_cache,
                                 budget_s, left)
        task_s = time.perf_counter() - t0
        got = [{**r, "machine_key": here, "task_s": task_s} for r in got]
        n_over += over
        rows.extend(got)
        counts[outcome_of(got)] += 1
        if flush_due():
            last_write = flush()
    if executor is None:
        cf_samples = {cid: [t] for cid, t in cf_cache.items()}
    if rounds > 1 and not policy.accuracy_only and executor is None:
        index: dict[tuple, list[int]] = {}
        for j, r in enumerate(rows):
            if r.get("outcome") == "ok" and r.get("run_id") == run_id:
                index.setdefault((r["case_id"], r["backend"], r["dtype"], r["method"], r["knob"]), []).append(j)
        todo_ok = [c for c in todo if tuple(map(str, c.key)) in index]
        for rnd in range(2, rounds + 1):
            for i, cfg in enumerate(todo_ok):
                if cfg.case.id not in cf_samples or len(cf_samples[cfg.case.id]) < rnd:
                    cf_samples.setdefault(cfg.case.id, []).append(closed_form_time(cfg.case, policy))
                if progress:
                    progress(i, len(todo_ok), f"round {rnd}/{rounds}: {cfg.case.id} {cfg.backend_id} {cfg.method}",
                             dict(counts))
                extra = retime(cfg, backends[cfg.backend_id], policy)
                for j in index[tuple(map(str, cfg.key))]:
                    _pool(rows[j], extra, float(np.median(cf_samples[cfg.case.id])))
            write_results(to_frame(rows), out_dir)
    if progress:
        progress(n_total, n_total, "done", dict(counts))
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
    df = to_frame(rows)
    write_results(df, out_dir)
    _elapsed(env, time.monotonic() - started)
    write_json(out_dir / "environment.json", env)
    return df
