"""The runner: plan (cases × backends × methods × dtypes × knobs), measure, record.

Every planned configuration becomes exactly one row: ``ok`` (measured), ``skipped`` (with the
reason: backend unavailable, method not implemented, scene lacks what the method needs, dtype
unsupported) or ``failed`` (the exception, and the run goes on).  Rows are written to disk
after every case, atomically, so a run that dies keeps what it finished.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import json
import secrets
import traceback
from pathlib import Path
from typing import Any, Callable

import numpy as np

from impls import Unavailable, get_method
from reference import Case, catalog
from reference.quadric import ray_sphere_roots

from . import environment
from .metrics import summarize
from .results import SCHEMA_VERSION, knob_string, to_frame, write_json, write_results
from .suites import Suite
from .timing import TimingPolicy, measure


@dataclasses.dataclass(frozen=True)
class Config:
    case: Case
    backend_id: str
    method: str
    dtype: str
    knobs: dict


def new_run_id() -> str:
    return _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%SZ") + "-" + secrets.token_hex(3)


def closed_form_time(case: Case, policy: TimingPolicy) -> float:
    """Median time of the exact closed-form ray–sphere intersection of ``case.n_rays`` rays in
    numpy float64 (:func:`reference.quadric.ray_sphere_roots`): the run's unit of time."""
    o, d = case.origins, case.directions
    timing, _ = measure(lambda: ray_sphere_roots(o, d, (0.0, 0.0, 0.0), 1.0), lambda _: None, policy)
    return timing.median_s


def _base_row(run_id: str, cfg: Config, backend: Any) -> dict:
    device = getattr(backend, "device", cfg.backend_id.partition(":")[2] or "cpu")
    return {
        "schema_version": SCHEMA_VERSION, "run_id": run_id, "case_id": cfg.case.id, "case_version": cfg.case.version,
        "backend": cfg.backend_id, "device": device, "dtype": cfg.dtype, "method": cfg.method,
        "knob": knob_string(cfg.knobs), "knobs_json": json.dumps(cfg.knobs, sort_keys=True), "n_rays": cfg.case.n_rays,
    }


def skip_reason(cfg: Config, backend: Any) -> str | None:
    if isinstance(backend, Unavailable):
        return f"backend unavailable: {backend.reason}"
    if cfg.method not in backend.methods():
        return f"{cfg.backend_id} does not implement {cfg.method}"
    if cfg.dtype not in backend.capabilities.dtypes:
        return f"{cfg.backend_id} does not support {cfg.dtype}"
    return get_method(cfg.method).skip_reason(cfg.case.scene)


def run_one(run_id: str, cfg: Config, backend: Any, policy: TimingPolicy, cf_time: float) -> dict:
    row = _base_row(run_id, cfg, backend)
    reason = skip_reason(cfg, backend)
    if reason:
        return {**row, "outcome": "skipped", "reason": reason}
    case = cfg.case
    try:
        prep = backend.prepare(cfg.method, case.scene, case.origins, case.directions, dtype=cfg.dtype,
                               t_min=case.t_min, t_max=case.t_max, **cfg.knobs)
        timing, out = measure(prep.run, backend.synchronize, policy)
        res = prep.result(out)
        if res.t.shape != (case.n_rays,):
            raise ValueError(f"result t has shape {res.t.shape}, expected ({case.n_rays},)")
        acc = summarize(res, case.exact_t, cfg.dtype)
    except Exception as exc:  # a failing configuration becomes a row; the run goes on
        return {**row, "outcome": "failed", "reason": f"{type(exc).__name__}: {exc}",
                "traceback": traceback.format_exc(limit=5)}
    return {
        **row, "outcome": "ok", "reason": "",
        "status_counts": json.dumps(res.status_counts(), sort_keys=True), **acc,
        "first_call_s": timing.first_call_s,
        "compile_s": prep.compile_s if prep.compile_s is not None else max(timing.first_call_s - timing.median_s, 0.0),
        "time_median_s": timing.median_s, "time_iqr_s": timing.iqr_s,
        "time_samples_s": json.dumps(timing.samples_s), "time_ratio_cf": timing.median_s / cf_time,
        "n_samples": len(timing.samples_s),
    }


def plan(suite: Suite, backend_ids: list[str], case_pattern: str | None, methods: list[str] | None,
         dtypes: list[str] | None) -> list[Config]:
    """Configurations in measuring order: knobs outer, backends inner, so backends interleave."""
    cfgs = []
    for case in catalog(case_pattern or suite.case_pattern):
        for method, sweep in suite.sweeps.items():
            if methods and method not in methods:
                continue
            for dtype in dtypes or suite.dtypes:
                for knobs in sweep:
                    for bid in backend_ids:
                        cfgs.append(Config(case, bid, method, dtype, dict(knobs)))
    return cfgs


def run(suite: Suite, backends: dict[str, Any], out_dir: Path, *, case_pattern: str | None = None,
        methods: list[str] | None = None, dtypes: list[str] | None = None, policy: TimingPolicy = TimingPolicy(),
        run_id: str | None = None, progress: Callable[[int, int, str], None] | None = None) -> "Any":
    """Run the plan, writing ``results.*`` and ``environment.json`` to ``out_dir``; returns the frame."""
    run_id = run_id or new_run_id()
    out_dir = Path(out_dir)
    env = environment.collect()
    env["run_id"] = run_id
    env["suite"] = suite.name
    for bid, b in backends.items():
        if not isinstance(b, Unavailable):
            env.update({f"backend.{bid}.{k}": v for k, v in b.versions().items()})
    write_json(out_dir / "environment.json", env)
    cfgs = plan(suite, list(backends), case_pattern, methods, dtypes)
    if not cfgs:
        raise ValueError(f"nothing to run: no case matches {case_pattern or suite.case_pattern!r} "
                         "or no method matches --method; `python -m bench cases` lists the cases")
    rows: list[dict] = []
    cf_cache: dict[str, float] = {}
    for i, cfg in enumerate(cfgs):
        if cfg.case.id not in cf_cache:
            if rows:
                write_results(to_frame(rows), out_dir)
            cf_cache[cfg.case.id] = closed_form_time(cfg.case, policy)
        if progress:
            progress(i, len(cfgs), f"{cfg.case.id} {cfg.backend_id} {cfg.method} {knob_string(cfg.knobs)}")
        rows.append(run_one(run_id, cfg, backends[cfg.backend_id], policy, cf_cache[cfg.case.id]))
    if progress:
        progress(len(cfgs), len(cfgs), "done")
    for cid, tcf in cf_cache.items():
        env[f"closed_form_s.{cid}"] = repr(tcf)
    write_json(out_dir / "environment.json", env)
    df = to_frame(rows)
    write_results(df, out_dir)
    return df
