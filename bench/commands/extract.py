"""``python -m bench extract``."""

from __future__ import annotations

import argparse
from pathlib import Path

from ._common import DEFAULT_REPORTS, ProgressLines, error, int_at_least

ORDER = 5
HELP = ("marching cubes (scikit-image) at several grid resolutions, scored by "
       "Hausdorff and Chamfer distance to the exact surface, with time (bench/studies/extraction.py)")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--case", help="glob(s) on case ids, comma-separated (default: one case per distinct scene and "
                    "the mesh cameras)")
    p.add_argument("--resolution", type=int_at_least(4), action="append",
                    help="grid points per axis, repeatable (default 16, 32, 64, 128)")
    p.add_argument("--repeats", type=int_at_least(1), default=3, help="timed repeats per configuration (default 3)")
    p.add_argument("--out", help="output directory (default: reports/extract-<run-id>/); never overwritten")


def run(args) -> int:
    from reference.cases import catalog

    from ..studies import extraction
    from ..run import runner
    from ..run.results import to_frame, write_atomic, write_results

    run_id = runner.new_run_id()
    out = Path(args.out) if args.out else DEFAULT_REPORTS / f"extract-{run_id}"
    if args.case:
        try:
            cases = catalog(args.case)
        except ValueError as exc:
            return error(f"--case: {exc}")
        if not cases:
            return error(f"--case: no case matches {args.case!r}; `python -m bench cases` lists them")
    else:
        cases = None
    from ..run.rundir import claim_out

    try:
        lock = claim_out(out)  # new or empty, created, and this process's alone until it exits
    except ValueError as exc:
        return error(str(exc))
    resolutions = tuple(args.resolution or (16, 32, 64, 128))
    from ..run.heartbeat import Heartbeat

    lines = ProgressLines(periodic=False)
    with Heartbeat(lines.line) as beat:  # a line as each configuration starts, and every 30 s of it
        rows = extraction.run_extraction(cases, resolutions=resolutions, repeats=args.repeats, run_id=run_id,
                                         progress=beat.say, stage=beat.stage)
    df = to_frame(rows)
    write_results(df, out)
    image = extraction.plot(df, out / "extraction.png")
    md = extraction.markdown_section(df, image=image.name if image else None)
    write_atomic(out / "extraction.md", lambda tmp: Path(tmp).write_text(md, encoding="utf-8"))
    print(md)
    print(f"wrote {out / 'results.csv'}, {out / 'extraction.md'}" + (f", {image}" if image else ""))
    lock.release()
    return 0

