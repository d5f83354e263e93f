"""``python -m bench claims``."""

from __future__ import annotations

import argparse
from pathlib import Path

from ._common import DEFAULT_REPORTS, error, make_console, reference_cache_dir, run_claims_into

ORDER = 2
HELP = ("check the lecture's claims; writes claims.csv, plots and a report")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", help="output directory (default: reports/claims-<run-id>/)")
    p.add_argument("--full", action="store_true", help="the full (slower) checks instead of the quick ones")
    p.add_argument("--only", nargs="+", metavar="ID", help="claim ids to check (default: all), e.g. --only 2 7 (a number stands for all its parts: 2 is 2a, 2b, 2c)")


def run(args) -> int:
    """Check the lecture's claims (all, or ``--only`` these ids; ``--full``: the full grids) into
    ``--out``: ``claims.csv``, one ``claim_<id>.png`` each, ``claims.md`` (the ledger as Markdown)
    and the report; a one-line-per-claim summary on stdout."""
    from ..run.results import write_atomic, write_json
    from ..run.runner import new_run_id
    from ..run.environment import collect

    if args.only:
        from ..claims import claim_ids
        from ..claims.ledger import LEDGER

        known = claim_ids()
        args.only = LEDGER.expand(args.only)  # "2": its parts 2a, 2b, 2c
        unknown = [i for i in args.only if i not in known]
        if unknown:
            return error(f"--only: unknown claim id(s) {', '.join(unknown)}; known ids are {', '.join(known)} "
                         "(a claim's number stands for all its parts: 2 is 2a, 2b and 2c)")
    from ..run.rundir import RunLock, make_dir

    out = Path(args.out) if args.out else DEFAULT_REPORTS / ("claims-" + new_run_id())
    try:  # created, and this process's alone until it exits (a run directory has one writer)
        RunLock(make_dir(out)).acquire()
    except ValueError as exc:
        return error(str(exc))
    except OSError as exc:
        return error(f"--out: cannot lock {out}: {exc.strerror or exc}; pass a directory you can write")
    held = [n for n in ("claims.csv", "claims.md") if (out / n).exists()]
    if held:
        return error(f"--out: {out} already holds {', '.join(held)}; results are never overwritten. Pass another --out")
    console = make_console()
    note = run_claims_into(out, quick=not args.full, console=console, only=args.only,
                           reference_dir=reference_cache_dir(args))
    if not (out / "environment.json").exists():
        write_json(out / "environment.json", {**collect(), "run_id": out.name, "suite": "claims"})
    if (out / "claims.csv").exists():
        from ..claims.summary import markdown_section, terminal_summary
        from ..report.build import build_from_dir
        from ..report.tables import read_claims

        claims = read_claims(out)
        md = markdown_section(claims)
        write_atomic(out / "claims.md", lambda p: Path(p).write_text(md, encoding="utf-8"))
        build_from_dir(out)
        console.print(terminal_summary(claims), markup=False)
        console.print(f"Report: {out / 'report.html'}")
        errors = [str(i) for i, v in zip(claims["id"], claims["verdict"]) if v == "error"]
        if errors:  # a check that could not run is no verdict: a CI job must see it ("fails" is a verdict)
            console.print(f"claims whose check could not run (verdict error): {', '.join(errors)}", markup=False)
            return 1
    return 1 if note else 0

