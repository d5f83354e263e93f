"""``python -m bench.claims [--out DIR] [--full] [--only ID ...]``: run the claims ledger on its own."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from . import run_claims, write_atomic
from .summary import markdown_section, terminal_summary


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.claims", description=__doc__)
    p.add_argument("--out", type=Path, default=Path("reports/claims"), help="folder for claims.csv, claims.md, PNGs")
    p.add_argument("--full", action="store_true", help="full grids (minutes) instead of the quick ones")
    p.add_argument("--only", nargs="+", metavar="ID", help="claim ids to run (default: all)")
    a = p.parse_args(argv)
    try:
        df = run_claims(a.out, quick=not a.full, only=a.only,
                        progress=lambda i, r: print(f"claim {i}: {r['verdict']} ({r['seconds']:.1f}s)", file=sys.stderr))
    except ValueError as exc:
        p.error(str(exc))
    md = markdown_section(df)
    write_atomic(a.out / "claims.md", lambda tmp: Path(tmp).write_text(md, encoding="utf-8"))
    print(terminal_summary(df))
    print(f"\nwrote {a.out / 'claims.csv'} and {a.out / 'claims.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
