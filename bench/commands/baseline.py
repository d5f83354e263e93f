"""``python -m bench baseline``."""

from __future__ import annotations

import argparse
from pathlib import Path

from ._common import DEFAULT_REPORTS

ORDER = 3
HELP = ("regenerate the accuracy baseline that CI compares against")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default=str(DEFAULT_REPORTS / "baseline"), help="default: reports/baseline")
    p.add_argument("--suite", default="quick")
    p.add_argument("--backend", action="append", help="backend ids (default: all available)")


def run(args) -> int:
    """Regenerate the committed accuracy baseline: an accuracy-only run of the suite (one call per
    configuration, no timing), kept as ``results.csv`` + ``environment.json`` only (text, diffable)."""
    import shutil
    import tempfile

    from . import main

    out = Path(args.out)
    with tempfile.TemporaryDirectory(prefix="isobench-baseline-") as tmp:
        rc = main(["run", "--suite", args.suite, "--accuracy-only", "--no-claims", "--no-stability", "--no-progress", "--out",
                   str(Path(tmp) / "run")] + sum((["--backend", b] for b in args.backend or []), []))
        if rc != 0:
            return rc
        out.mkdir(parents=True, exist_ok=True)
        from ..run.results import read_results, write_atomic

        df = read_results(Path(tmp) / "run")
        # wall-clock columns differ on every run: blank them so the committed file changes only
        # when accuracy does
        for col in ("first_call_s", "compile_s", "time_median_s", "time_iqr_s", "time_ratio_cf"):
            df[col] = float("nan")
        df["compile_cache"] = None  # whether a kernel was in the cache depends on the machine's history
        df.to_csv(Path(tmp) / "run" / "results.csv", index=False)
        for name in ("results.csv", "environment.json"):
            write_atomic(out / name, lambda p, src=Path(tmp) / "run" / name: shutil.copyfile(src, p))
        stale = out / "results.parquet"
        if stale.exists():
            stale.unlink()
    print(f"baseline written to {out}; compare a run with: python -m bench compare {out} RUN_DIR")
    return 0

