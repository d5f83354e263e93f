"""``python -m bench report``."""

from __future__ import annotations

import argparse
from pathlib import Path

from ._common import error

ORDER = 8
HELP = ("rebuild report.md/html of a run directory")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run_dir")


def run(args) -> int:
    from ..report.build import build_from_dir

    run_dir = Path(args.run_dir)
    if not run_dir.is_dir():
        return error(f"RUN_DIR: {run_dir} is not a directory; pass the --out directory of a `bench run`")
    if not (run_dir / "environment.json").exists():
        return error(f"RUN_DIR: {run_dir} holds no environment.json, so it is not a run directory; pass the --out "
                      "directory of a `bench run` or `bench claims`")
    try:
        build_from_dir(run_dir)
    except ValueError as exc:  # a corrupt results file or environment.json (read_results names the file)
        return error(f"RUN_DIR: {exc}")
    print(run_dir / "report.html")
    return 0

