"""``python -m bench``: run suites, compare runs, list cases and backends.

    python -m bench run --suite quick [--backend numpy,jax:cpu] [--case 'sphere.*'] [--out DIR]
    python -m bench compare BASE NEW [--timing] [--factor 1.1]
    python -m bench cases [--tag grazing]
    python -m bench backends
    python -m bench report RUN_DIR
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from .environment import ROOT

DEFAULT_REPORTS = ROOT / "reports"


def _split(values: list[str] | None) -> list[str] | None:
    if not values:
        return None
    return [v for item in values for v in item.split(",") if v]


def _console():
    from rich.console import Console

    import os

    return Console(highlight=False, width=None if os.isatty(1) else 200)


def cmd_run(args) -> int:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
    from rich.table import Table

    from impls import registry

    from . import report, runner
    from .suites import get_suite
    from .timing import TimingPolicy

    suite = get_suite(args.suite)
    ids = _split(args.backend) or registry.default_ids()
    backends = {bid: registry.resolve(bid) for bid in ids}
    console = _console()
    for bid, b in backends.items():
        if isinstance(b, registry.Unavailable):
            console.print(f"[yellow]backend {bid} unavailable, its rows are skipped:[/] {b.reason}")
    run_id = runner.new_run_id()
    out = Path(args.out) if args.out else DEFAULT_REPORTS / run_id
    if (out / "results.parquet").exists():
        console.print(f"[red]{out} already holds results; results are never overwritten. Pass another --out.[/]")
        return 2
    policy = TimingPolicy(min_repeats=args.min_repeats, min_time_s=args.min_time)
    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=console, disable=args.no_progress or not console.is_terminal) as prog:
        task = prog.add_task("planning", total=None)

        def progress(i, n, what):
            prog.update(task, total=n, completed=i, description=what[:70])

        try:
            df = runner.run(suite, backends, out, case_pattern=args.case, methods=_split(args.method),
                            dtypes=_split(args.dtype), policy=policy, run_id=run_id, progress=progress)
        except ValueError as exc:
            console.print(f"[red]error:[/] {exc}")
            return 2
    env = json.loads((out / "environment.json").read_text())
    report.build(df, env, out)
    summ = report.summary_table(df)
    table = Table(title=f"isobench {suite.name} — run {run_id}")
    for c in summ.columns:
        table.add_column(c, justify="left" if c in ("case", "method", "dtype", "backend", "at knob") else "right")
    for _, r in summ.iterrows():
        table.add_row(*[f"{v:.3g}" if isinstance(v, float) else str(v) for v in r])
    console.print(table)
    n_ok, n_skip, n_fail = ((df["outcome"] == o).sum() for o in ("ok", "skipped", "failed"))
    console.print(f"{n_ok} configurations ran, {n_skip} skipped, {n_fail} failed. Report: {out / 'report.html'}")
    return 0


def cmd_compare(args) -> int:
    from . import compare as cmp
    from .results import read_results, write_text

    base, new = read_results(args.base), read_results(args.new)
    same_machine = True
    try:
        from .environment import machine_key

        eb = json.loads((Path(args.base) / "environment.json").read_text())
        en = json.loads((Path(args.new) / "environment.json").read_text())
        same_machine = machine_key(eb) == machine_key(en)
    except (OSError, ValueError):
        pass
    res = cmp.compare(base, new, factor=args.factor, alpha=args.alpha, rtol=args.rtol, same_machine=same_machine)
    console = _console()
    counts = {col: res[col].value_counts().to_dict() for col in ("accuracy", "timing")}
    worse = res[(res["accuracy"] == "worse") | ((res["timing"] == "worse") & args.timing)]
    if args.out:
        write_text(Path(args.out), res.to_csv(index=False))
    if len(worse):
        console.print(worse.to_string(index=False))
    console.print(f"accuracy: {counts['accuracy']}")
    console.print(f"timing:   {counts['timing']}" + ("" if same_machine else " (different machines: timing not compared)"))
    if len(worse):
        console.print(f"[red]{len(worse)} regression(s)[/]")
        return 1
    console.print("no regression")
    return 0


def cmd_cases(args) -> int:
    from reference import catalog

    for c in catalog(args.case, set(_split(args.tag) or [])):
        print(f"{c.id:40s} v{c.version}  rays={c.n_rays:<6d} tags={','.join(c.tags)}  {c.description}")
    return 0


def cmd_backends(args) -> int:
    from impls import registry

    for bid in registry.default_ids():
        b = registry.resolve(bid)
        if isinstance(b, registry.Unavailable):
            print(f"{bid:12s} unavailable: {b.reason}")
        else:
            caps = b.capabilities
            print(f"{bid:12s} methods={','.join(b.methods())} dtypes={','.join(caps.dtypes)} autodiff={caps.autodiff} jit={caps.jit}")
    return 0


def cmd_report(args) -> int:
    from .report import build_from_dir

    build_from_dir(Path(args.run_dir))
    print(Path(args.run_dir) / "report.html")
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench", description="isobench: verify and time implicit-surface methods")
    sub = p.add_subparsers(dest="cmd", required=True)

    r = sub.add_parser("run", help="run a suite and write results and a report")
    r.add_argument("--suite", default="quick", help="quick (CI, < 2 min) or full")
    r.add_argument("--backend", action="append", help="backend ids, comma-separated or repeated (default: all available)")
    r.add_argument("--method", action="append", help="methods to run (default: all in the suite)")
    r.add_argument("--case", help="glob(s) on case ids, comma-separated (default: the suite's)")
    r.add_argument("--dtype", action="append", help="float64 and/or float32 (default: the suite's)")
    r.add_argument("--out", help="output directory (default: reports/<run-id>/)")
    r.add_argument("--min-time", type=float, default=0.2, help="seconds of timed calls per configuration (default 0.2)")
    r.add_argument("--min-repeats", type=int, default=5, help="timed calls per configuration at least (default 5)")
    r.add_argument("--no-progress", action="store_true", help="no progress bar")
    r.set_defaults(fn=cmd_run)

    c = sub.add_parser("compare", help="compare two runs; exit 1 on regression")
    c.add_argument("base")
    c.add_argument("new")
    c.add_argument("--factor", type=float, default=1.1, help="timing: slower by more than this factor … (default 1.1)")
    c.add_argument("--alpha", type=float, default=0.01, help="… and significant at this level (default 0.01)")
    c.add_argument("--rtol", type=float, default=0.1, help="accuracy: relative slack on the max error (default 0.1)")
    c.add_argument("--timing", action="store_true", help="also fail on significant timing regressions")
    c.add_argument("--out", help="write the comparison table as csv")
    c.set_defaults(fn=cmd_compare)

    k = sub.add_parser("cases", help="list the case catalog")
    k.add_argument("--case", help="glob on ids")
    k.add_argument("--tag", action="append", help="only cases with these tags")
    k.set_defaults(fn=cmd_cases)

    b = sub.add_parser("backends", help="list backends and what they can do")
    b.set_defaults(fn=cmd_backends)

    rp = sub.add_parser("report", help="rebuild report.md/html of a run directory")
    rp.add_argument("run_dir")
    rp.set_defaults(fn=cmd_report)

    args = p.parse_args(argv)
    return args.fn(args)


if __name__ == "__main__":
    sys.exit(main())
