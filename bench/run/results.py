"""Result rows: schema, atomic writing, reading.

Long format: one flat row per (run, case, case version, backend, device, dtype, method, knob,
quantity) — a configuration that checks several quantities (a normal and a curvature) has one
row per quantity, with the same timing.  Lists and dicts (timing samples, status counts, knob
values) are stored as JSON strings so the same table round-trips through parquet and csv.

Schema history: 1 — the skeleton (depth only); 2 — ``family``, ``quantity``, ``unit``,
``error_rel_max``, ``error_ulps_max``, ``n_checked``, ``n_declined``, ``loops``, ``rounds``,
``error_iterate_median``, ``reference_error_bound``, ``timing_note``; ``driver_json`` (the
backend's loop-driver settings, :func:`bench.run.environment.driver_record`; added without a version
bump: readers treat it as optional); ``machine_key`` (:func:`bench.run.environment.machine_key` of the
process that measured the row: timings are comparable only between equal keys), ``worker`` and
``worker_pid`` (the dask worker's address and process id; empty in a single-process run) and
``task_s`` (wall seconds of the whole configuration on its process, closed-form unit and
reference answers included: what :mod:`bench.run.cluster`'s spread and projection read), added the
same way; ``n_not_judged`` (depth rows: rays the reference flags, left out of the errors and of the
false hit/miss counts, :func:`bench.run.metrics.judged_rays`; empty in older rows, read as 0), also.
"""

from __future__ import annotations

import json
import os
import secrets
from pathlib import Path

import pandas as pd

SCHEMA_VERSION = 2

#: columns every results table has, in this order (more may follow)
COLUMNS = [
    "schema_version", "run_id", "case_id", "case_version", "backend", "device", "dtype", "method", "family", "knob",
    "quantity", "unit", "outcome", "reason", "n_rays", "status_counts", "error_max", "error_p99", "error_median",
    "error_max_finite", "error_rel_max", "error_ulps_max", "error_max_eps", "n_checked", "n_declined",
    "n_false_hit", "n_false_miss", "n_not_judged", "evals_per_ray", "evals_p99", "evals_max", "iterations_max",
    "first_call_s", "compile_s", "time_median_s", "time_iqr_s", "time_samples_s", "time_ratio_cf", "n_samples",
    "loops", "rounds", "error_iterate_median", "reference_error_bound", "reference_s", "knobs_json", "timing_note", "traceback", "driver_json",
    "machine_key", "worker", "worker_pid", "task_s", "compile_cache",
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


#: what a temporary file of :func:`write_atomic` looks like: ``.<name>.<random>.tmp`` next to
#: the file it becomes; never a result, removed on resume
TEMP_GLOB = ".*.tmp"


def write_atomic(path: Path, write) -> None:
    """``write(tmp)`` into a fresh temporary file next to ``path``, then ``os.replace`` it onto
    ``path``: a reader sees the old file or the new one, never half of one.  The one atomic
    writer of isobench (results, environment, reports, claims, cached references).

    ``write`` receives the temporary path as a string and must write to exactly that path
    (the name ends in ``.tmp``: pass the format explicitly where a writer infers it from the
    suffix, e.g. ``savefig(tmp, format="png")``, and give ``np.savez`` an open file, since it
    appends ``.npz`` to a name without it).  The temporary file is created with mode 0666 less
    the process umask (0644 under umask 022), as ``open`` would create ``path`` itself
    (``mkstemp``'s 0600 would make shared results unreadable).  Missing parent folders are
    created."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    while True:
        tmp = path.parent / f".{path.name}.{secrets.token_hex(4)}.tmp"
        try:
            os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
            break
        except FileExistsError:  # pragma: no cover - 2^-32
            continue
    try:
        write(str(tmp))
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def remove_temporaries(out_dir: Path) -> list[Path]:
    """Delete what killed writers left in ``out_dir`` (temporary files matching
    :data:`TEMP_GLOB`, often 0 bytes); returns them.  Only for a directory no other process is
    writing to (``--resume``)."""
    gone = []
    for p in Path(out_dir).glob(TEMP_GLOB):
        if p.is_file():
            p.unlink()
            gone.append(p)
    return gone


def write_text(path: Path, text: str) -> None:
    write_atomic(Path(path), lambda p: Path(p).write_text(text, encoding="utf-8"))


def write_results(df: pd.DataFrame, out_dir: Path) -> None:
    """Write ``results.parquet`` and ``results.csv`` atomically (temp file + rename)."""
    out_dir = Path(out_dir)
    write_atomic(out_dir / "results.parquet", lambda p: df.to_parquet(p, index=False))
    write_atomic(out_dir / "results.csv", lambda p: df.to_csv(p, index=False))


def write_json(path: Path, obj) -> None:
    write_text(path, json.dumps(obj, indent=2, sort_keys=True, default=str))


def read_results(path: str | Path) -> pd.DataFrame:
    """Read a results table from a run directory or a .parquet/.csv file.  FileNotFoundError when
    there is none; ValueError naming the file when it cannot be read or is not a results table
    (lacks the key columns)."""
    p = Path(path)
    if p.is_dir():
        p = p / "results.parquet" if (p / "results.parquet").exists() else p / "results.csv"
    if not p.exists():
        raise FileNotFoundError(f"no results at {path}: expected a run directory or a results.parquet/.csv file")
    try:
        df = pd.read_parquet(p) if p.suffix == ".parquet" else pd.read_csv(p, keep_default_na=False, na_values=[""])
    except Exception as exc:  # pyarrow, pandas and the OS raise many kinds; the file is what is wrong
        raise ValueError(f"cannot read {p}: {type(exc).__name__}: {str(exc)[:200]}; is it an isobench results "
                         f"file, complete?") from None
    if "quantity" not in df.columns:  # schema 1: every row was a depth row
        df["quantity"] = "depth"
    lacking = [c for c in KEY + ["outcome"] if c not in df.columns]
    if lacking:
        raise ValueError(f"{p} is not an isobench results table: it lacks the columns {lacking}")
    for c in KEY:
        df[c] = df[c].fillna("").astype(str)
    if "schema_version" in df.columns and len(df):
        try:
            version = int(df["schema_version"].iloc[0])
        except (TypeError, ValueError):
            raise ValueError(f"{p}: schema_version {df['schema_version'].iloc[0]!r} is not a number") from None
        if version > SCHEMA_VERSION:
            raise ValueError(f"{p} has schema version {version}, newer than this isobench ({SCHEMA_VERSION})")
    return df
