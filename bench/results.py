"""Result rows: schema, atomic writing, reading.

Long format: one flat row per (run, case, case version, backend, device, dtype, method, knob,
quantity) — a configuration that checks several quantities (a normal and a curvature) has one
row per quantity, with the same timing.  Lists and dicts (timing samples, status counts, knob
values) are stored as JSON strings so the same table round-trips through parquet and csv.

Schema history: 1 — the skeleton (depth only); 2 — ``family``, ``quantity``, ``unit``,
``error_rel_max``, ``error_ulps_max``, ``n_checked``, ``n_declined``, ``loops``, ``rounds``,
``error_iterate_median``, ``reference_error_bound``, ``timing_note``.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import pandas as pd

SCHEMA_VERSION = 2

#: columns every results table has, in this order (more may follow)
COLUMNS = [
    "schema_version", "run_id", "case_id", "case_version", "backend", "device", "dtype", "method", "family", "knob",
    "quantity", "unit", "outcome", "reason", "n_rays", "status_counts", "error_max", "error_p99", "error_median",
    "error_max_finite", "error_rel_max", "error_ulps_max", "error_max_eps", "n_checked", "n_declined",
    "n_false_hit", "n_false_miss", "evals_per_ray", "evals_p99", "evals_max", "iterations_max",
    "first_call_s", "compile_s", "time_median_s", "time_iqr_s", "time_samples_s", "time_ratio_cf", "n_samples",
    "loops", "rounds", "error_iterate_median", "reference_error_bound", "reference_s", "knobs_json", "timing_note", "traceback",
]
#: the reason of a configuration skipped because its run's time budget ran out (prefix)
OVER_BUDGET = "over the run's time budget"

#: what identifies a row across runs (compare matches on it)
KEY = ["case_id", "backend", "dtype", "method", "knob", "quantity"]


def knob_string(knobs: dict) -> str:
    """Canonical, human-readable knob id: ``max_steps=512,tol=1e-06`` (sorted by name)."""
    return ",".join(f"{k}={knobs[k]:g}" if isinstance(knobs[k], float) else f"{k}={knobs[k]}" for k in sorted(knobs))


def to_frame(rows: list[dict]) -> pd.DataFrame:
    df = pd.DataFrame(rows)
    for c in COLUMNS:
        if c not in df.columns:
            df[c] = None
    extra = [c for c in df.columns if c not in COLUMNS]
    return df[COLUMNS + extra]


def _atomic_write(path: Path, write) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def write_text(path: Path, text: str) -> None:
    _atomic_write(Path(path), lambda p: Path(p).write_text(text, encoding="utf-8"))


def write_results(df: pd.DataFrame, out_dir: Path) -> None:
    """Write ``results.parquet`` and ``results.csv`` atomically (temp file + rename)."""
    out_dir = Path(out_dir)
    _atomic_write(out_dir / "results.parquet", lambda p: df.to_parquet(p, index=False))
    _atomic_write(out_dir / "results.csv", lambda p: df.to_csv(p, index=False))


def write_json(path: Path, obj) -> None:
    write_text(path, json.dumps(obj, indent=2, sort_keys=True, default=str))


def read_results(path: str | Path) -> pd.DataFrame:
    """Read a results table from a run directory or a .parquet/.csv file."""
    p = Path(path)
    if p.is_dir():
        p = p / "results.parquet" if (p / "results.parquet").exists() else p / "results.csv"
    if not p.exists():
        raise FileNotFoundError(f"no results at {path}: expected a run directory or a results.parquet/.csv file")
    df = pd.read_parquet(p) if p.suffix == ".parquet" else pd.read_csv(p, keep_default_na=False, na_values=[""])
    if "quantity" not in df.columns:  # schema 1: every row was a depth row
        df["quantity"] = "depth"
    for c in KEY:
        df[c] = df[c].fillna("").astype(str)
    if "schema_version" in df.columns and len(df) and int(df["schema_version"].iloc[0]) > SCHEMA_VERSION:
        raise ValueError(f"{p} has schema version {df['schema_version'].iloc[0]}, newer than this isobench ({SCHEMA_VERSION})")
    return df
