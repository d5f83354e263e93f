"""``python -m bench spread``."""

from __future__ import annotations

import argparse
from pathlib import Path

from ._common import error, int_at_least, seconds

ORDER = 6
HELP = ("how a run was spread over processes (workers, machine keys, tasks per "
       "worker, wall and task time) and its projected wall time on more workers (bench/report/spread.py)")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run_dir")
    p.add_argument("--workers", type=int_at_least(1), nargs="+", help="worker counts to project (default 1 2 4 8 16 "
                     "32 64)")
    p.add_argument("--overhead-s", type=seconds, help="per-task overhead o in seconds (default: the run's measured "
                     "value; a single-process run has none)")
    p.add_argument("--central-s", type=seconds, help="central (scheduler and client) seconds per task c (default: the "
                     "run's measured value)")


def run(args) -> int:
    from ..report import spread

    run_dir = Path(args.run_dir)
    if not (run_dir / "environment.json").exists():
        return error(f"RUN_DIR: {run_dir} holds no environment.json; pass the --out directory of a `bench run`")
    try:
        print(spread.text(run_dir, tuple(args.workers or spread.WORKERS), args.overhead_s, args.central_s))
    except (ValueError, FileNotFoundError) as exc:
        return error(f"RUN_DIR: {exc}")
    return 0

