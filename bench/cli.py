"""``python -m bench``: run suites, compare runs, list cases and backends.

    python -m bench run --suite quick [--backend numpy,jax:cpu] [--method sphere_trace] [--case 'sphere.*']
                        [--dtype float64] [--out DIR] [--resume] [--threads 1] [--allocator tuned|default]
                        [--accuracy-only] [--no-claims] [--no-stability]
    python -m bench speed [--backend numpy,torch,jax] [--method hybrid_secant] [--repeats 3] [--threads 1]
                          [--allocator tuned|default]
    python -m bench compare BASE NEW [--timing] [--factor 1.1]
    python -m bench claims [--out DIR] [--full]
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


def run_claims_into(out: Path, *, quick: bool, console) -> str:
    """Call the claims ledger (``bench.claims.run_claims``) into ``out``; never raises.  Returns
    a one-line note for the report and the console ("" when it worked)."""
    try:
        from .claims import run_claims

        df = run_claims(out, quick=quick)
        n = 0 if df is None else len(df)
        console.print(f"claims: {n} checked, ledger in {out / 'claims.csv'}")
        return ""
    except Exception as exc:  # the ledger is a section of the report, never a reason to crash
        note = f"claims failed: {type(exc).__name__}: {exc}"
        console.print(f"[yellow]{note}[/]")
        return note


def run_stability_into(out: Path, suite, backends: dict, args, console) -> str:
    """The suite's stability stage (:func:`bench.stability.run_stage`) into ``out/stability``;
    never raises.  Returns "" or a note saying why it did not complete."""
    import time

    from .report import STABILITY_DIR
    from .stability import run_stage

    started = time.monotonic()
    try:
        from impls.registry import Unavailable

        ok = {b: v for b, v in backends.items() if not isinstance(v, Unavailable)}
        df = run_stage(suite, ok, out / STABILITY_DIR, timeout_s=args.timeout, resume=args.resume,
                       env_extra={"threads": str(args.threads)})
    except Exception as exc:  # the stage must not cost the run its report
        note = f"stability stage failed: {type(exc).__name__}: {exc}"
        console.print(f"[red]{note}[/]")
        return note
    console.print(f"stability: {len(df)} rows in {time.monotonic() - started:.1f} s, in {out / STABILITY_DIR}")
    return ""


def cmd_run(args) -> int:
    from .environment import configure_threads

    configure_threads(args.threads)  # before any array library is imported
    if args.allocator == "tuned":
        from .environment import tune_allocator

        tune_allocator()
    from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                               TimeRemainingColumn)
    from rich.table import Table

    from impls import registry

    from . import report, runner
    from .results import write_json
    from .suites import get_suite
    from .timing import TimingPolicy

    console = _console()
    try:
        suite = get_suite(args.suite)
    except ValueError as exc:
        console.print(f"[red]error:[/] {exc}")
        return 2
    if not runner.select_cases(suite, args.case):  # fail fast, before importing any backend
        console.print(f"[red]error:[/] nothing to run: no case matches {args.case or suite.case_pattern!r}; "
                      "`python -m bench cases` lists the cases")
        return 2
    if args.resume and not args.out:
        console.print("[red]--resume needs --out DIR: the run directory to finish[/]")
        return 2
    ids = _split(args.backend) or registry.default_ids()
    backends = {bid: registry.resolve(bid) for bid in ids}
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(args.threads)
    for bid, b in backends.items():
        if isinstance(b, registry.Unavailable):
            console.print(f"[yellow]backend {bid} unavailable, its rows are skipped:[/] {b.reason}")
    run_id = runner.new_run_id()
    out = Path(args.out) if args.out else DEFAULT_REPORTS / run_id
    if (out / "results.parquet").exists() and not args.resume:
        console.print(f"[red]{out} already holds results; results are never overwritten. "
                      "Pass another --out, or --resume to finish an interrupted run.[/]")
        return 2
    try:
        min_time = suite.min_time_s if args.min_time is None else args.min_time
        min_repeats = suite.min_repeats if args.min_repeats is None else args.min_repeats
        policy = TimingPolicy(min_repeats=min_repeats, min_time_s=min_time, timeout_s=args.timeout,
                              accuracy_only=args.accuracy_only, max_time_s=max(args.max_time, min_time))
    except ValueError as exc:
        console.print(f"[red]error:[/] {exc}")
        return 2
    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  TimeRemainingColumn(), console=console, disable=args.no_progress or not console.is_terminal) as prog:
        task = prog.add_task("planning", total=None)

        def progress(i, n, what):
            prog.update(task, total=n, completed=i, description=what[:70])

        try:
            df = runner.run(suite, backends, out, case_pattern=args.case, methods=_split(args.method),
                            dtypes=_split(args.dtype), policy=policy, run_id=run_id, progress=progress,
                            resume=args.resume, env_extra={"threads": str(args.threads)}, budget_s=suite.budget_s if args.budget is None else (args.budget or None),
                            rounds=args.rounds, reference_cache_dir=None if args.no_reference_cache
                            else DEFAULT_REPORTS / ".refcache", reference_timeout_s=args.reference_timeout)
        except ValueError as exc:
            console.print(f"[red]error:[/] {exc}")
            return 2
    env = json.loads((out / "environment.json").read_text())
    if suite.stability and not (args.no_stability or args.case or args.method or args.dtype):
        note = run_stability_into(out, get_suite(suite.stability), backends, args, console)
        env["stability"] = note or "ran"
        write_json(out / "environment.json", env)
    if not args.no_claims:
        note = run_claims_into(out, quick=suite.name == "quick", console=console)
        env["claims"] = note or "ran"
        write_json(out / "environment.json", env)
    report.build(df, env, out)
    summ = report.summary_table(df)
    table = Table(title=f"isobench {suite.name} — run {env['run_id']}")
    from rich.markup import escape

    for c in summ.columns:
        table.add_column(escape(c), justify="left" if c in ("case", "method", "quantity", "dtype", "backend", "at knob") else "right")
    for _, r in summ.iterrows():
        table.add_row(*[f"{v:.3g}" if isinstance(v, float) else str(v) for v in r])
    console.print(table)
    configs = report.config_outcomes(df)
    n_ok, n_skip, n_fail = ((configs["outcome"] == o).sum() for o in ("ok", "skipped", "failed"))
    console.print(f"{n_ok} configurations ran, {n_skip} skipped, {n_fail} failed in {env.get('elapsed_s', '?')} s. "
                  f"Report: {out / 'report.html'}")
    nominal = {"quick": 120.0, "full": 900.0}.get(suite.name)
    if nominal and float(env.get("elapsed_s", 0)) > nominal:
        console.print(f"[yellow]the {suite.name} suite took longer than its budget of {nominal:g} s; "
                      "select less with --case/--method, or lower --min-time[/]")
    return 0


def cmd_compare(args) -> int:
    from . import compare as cmp
    from .results import read_results, write_text

    try:
        base, new = read_results(args.base), read_results(args.new)
    except (FileNotFoundError, ValueError) as exc:
        print(f"error: {exc}")
        return 2
    same_machine = True
    try:
        from .environment import machine_key

        eb = json.loads((Path(args.base) / "environment.json").read_text())
        en = json.loads((Path(args.new) / "environment.json").read_text())
        same_machine = machine_key(eb) == machine_key(en)
    except (OSError, ValueError):
        pass
    try:
        res = cmp.compare(base, new, factor=args.factor, alpha=args.alpha, rtol=args.rtol, atol_eps=args.atol_eps,
                          same_machine=same_machine)
    except ValueError as exc:
        print(f"error: {exc}")
        return 2
    console = _console()
    counts = {col: res[col].value_counts().to_dict() for col in ("accuracy", "timing")}
    worse = res[(res["accuracy"] == "worse") | ((res["timing"] == "worse") & args.timing)]
    if args.out:
        write_text(Path(args.out), res.to_csv(index=False))
    if len(worse):
        from rich.markup import escape

        cols = [c for c in ["case_id", "backend", "dtype", "method", "knob", "quantity", "accuracy", "error_base",
                            "error_new", "timing", "time_ratio", "p_value", "note"] if c in worse.columns]
        console.print(escape(worse[cols].to_string(index=False)))
    console.print(f"accuracy: {counts['accuracy']}")
    console.print(f"timing:   {counts['timing']}" + ("" if same_machine else " (different machines: timing not compared)"))
    if len(worse):
        console.print(f"[red]{len(worse)} regression(s)[/]")
        return 1
    console.print("no regression")
    return 0


def cmd_claims(args) -> int:
    from .results import write_json
    from .runner import new_run_id
    from .environment import collect

    out = Path(args.out) if args.out else DEFAULT_REPORTS / ("claims-" + new_run_id())
    console = _console()
    note = run_claims_into(out, quick=not args.full, console=console)
    if not (out / "environment.json").exists():
        write_json(out / "environment.json", {**collect(), "run_id": out.name, "suite": "claims"})
    if (out / "claims.csv").exists():
        from .report import build_from_dir

        build_from_dir(out)
        console.print(f"Report: {out / 'report.html'}")
    return 1 if note else 0


def cmd_baseline(args) -> int:
    """Regenerate the committed accuracy baseline: an accuracy-only run of the suite (one call per
    configuration, no timing), kept as ``results.csv`` + ``environment.json`` only (text, diffable)."""
    import shutil
    import tempfile

    out = Path(args.out)
    with tempfile.TemporaryDirectory(prefix="isobench-baseline-") as tmp:
        rc = main(["run", "--suite", args.suite, "--accuracy-only", "--no-claims", "--no-stability", "--no-progress", "--out",
                   str(Path(tmp) / "run")] + sum((["--backend", b] for b in args.backend or []), []))
        if rc != 0:
            return rc
        out.mkdir(parents=True, exist_ok=True)
        from .results import read_results

        df = read_results(Path(tmp) / "run")
        # wall-clock columns differ on every run: blank them so the committed file changes only
        # when accuracy does
        for col in ("first_call_s", "compile_s", "time_median_s", "time_iqr_s", "time_ratio_cf"):
            df[col] = float("nan")
        df.to_csv(Path(tmp) / "run" / "results.csv", index=False)
        for name in ("results.csv", "environment.json"):
            shutil.copyfile(Path(tmp) / "run" / name, out / (name + ".tmp"))
            (out / (name + ".tmp")).replace(out / name)
        stale = out / "results.parquet"
        if stale.exists():
            stale.unlink()
    print(f"baseline written to {out}; compare a run with: python -m bench compare {out} RUN_DIR")
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


def cmd_speed(args) -> int:
    import json

    from . import environment, speed
    from impls import registry

    environment.configure_threads(args.threads)
    allocator = environment.tune_allocator() if args.allocator == "tuned" else "default"
    ids = _split(args.backend) if args.backend else [b.id for b in registry.available()[0]]
    knobs = json.loads(args.knobs) if args.knobs else {}
    rows = speed.measure(ids, n_side=args.side, method=args.method, repeats=args.repeats, knobs=knobs)
    for row in rows:
        row["threads"] = args.threads
        row["allocator"] = allocator
    print(f"{args.side}² rays, {args.method}, {args.threads} thread(s) per library and root-finder driver, "
          f"allocator: {allocator}; × unit = time / numpy closed-form sphere hit of the same rays (same run, 1 thread)")
    print(speed.format_rows(rows))
    if args.out:
        from .results import write_json

        write_json(Path(args.out), rows)
    return 0


ALLOCATOR_HELP = ("tuned (default): glibc keeps freed memory instead of mmapping and faulting in fresh pages for "
                  "every large temporary (bench.environment.tune_allocator; recorded); default: leave malloc alone")


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
    r.add_argument("--min-time", type=float, default=None, help="seconds of timed calls per configuration "
                   "(default: the suite's, 0.05 quick, 0.1 full)")
    r.add_argument("--max-time", type=float, default=5.0, help="seconds of timed calls per configuration at most (default 5)")
    r.add_argument("--min-repeats", type=int, default=None, help="timing samples per configuration at least "
                   "(default: the suite's, 3 quick, 5 full)")
    r.add_argument("--timeout", type=float, default=120.0, help="hard limit per configuration in seconds; past it the "
                   "configuration is a failed 'timeout' row and the run goes on (default 120, 0: none)")
    r.add_argument("--threads", type=int, default=1, help="threads per library (BLAS/OpenMP, torch, XLA), fixed and "
                   "recorded (default 1)")
    r.add_argument("--allocator", choices=("tuned", "default"), default="tuned", help=ALLOCATOR_HELP)
    r.add_argument("--accuracy-only", action="store_true", help="one call per configuration, no timing samples "
                   "(deterministic, for baselines)")
    r.add_argument("--resume", action="store_true", help="finish the interrupted run in --out DIR")
    r.add_argument("--rounds", type=int, default=1, help="time the whole plan this many times, round after round, "
                   "and pool the samples (robust run-to-run timing comparisons on a shared machine; default 1)")
    r.add_argument("--budget", type=float, default=None, help="wall-clock seconds for the run; configurations left "
                   "when it is spent become skipped rows saying so (default: the suite's, 100 quick, 840 full; 0: none)")
    r.add_argument("--no-claims", action="store_true", help="do not run the claims ledger at the end")
    r.add_argument("--no-stability", action="store_true", help="do not run the suite's stability stage (every root "
                   "finder × dtype on one case per adversarial ray family, accuracy only, into stability/)")
    r.add_argument("--reference-timeout", type=float, default=30.0, help="seconds for one costly reference answer (a "
                   "rendering integral for one case and density); past it that quantity is skipped with the reason, "
                   "and that density is not retried in this run (default 30, 0: none)")
    r.add_argument("--no-reference-cache", action="store_true", help="recompute costly reference answers (the "
                   "rendering integral) instead of reusing reports/.refcache/")
    r.add_argument("--no-progress", action="store_true", help="no progress bar")
    r.set_defaults(fn=cmd_run)

    c = sub.add_parser("compare", help="compare two runs; exit 1 on regression")
    c.add_argument("base")
    c.add_argument("new")
    c.add_argument("--factor", type=float, default=1.1, help="timing: slower by more than this factor … (default 1.1)")
    c.add_argument("--alpha", type=float, default=0.01, help="… and significant at this level (default 0.01)")
    c.add_argument("--rtol", type=float, default=0.1, help="accuracy: relative slack on the max error (default 0.1)")
    c.add_argument("--atol-eps", type=float, default=1000.0, help="accuracy: absolute slack in units of the row's "
                   "dtype eps (default 1000)")
    c.add_argument("--timing", action="store_true", help="also fail on significant timing regressions")
    c.add_argument("--out", help="write the comparison table as csv")
    c.set_defaults(fn=cmd_compare)

    cl = sub.add_parser("claims", help="check the lecture's claims; writes claims.csv, plots and a report")
    cl.add_argument("--out", help="output directory (default: reports/claims-<run-id>/)")
    cl.add_argument("--full", action="store_true", help="the full (slower) checks instead of the quick ones")
    cl.set_defaults(fn=cmd_claims)

    bl = sub.add_parser("baseline", help="regenerate the accuracy baseline that CI compares against")
    bl.add_argument("--out", default=str(DEFAULT_REPORTS / "baseline"), help="default: reports/baseline")
    bl.add_argument("--suite", default="quick")
    bl.add_argument("--backend", action="append", help="backend ids (default: all available)")
    bl.set_defaults(fn=cmd_baseline)

    k = sub.add_parser("cases", help="list the case catalog")
    k.add_argument("--case", help="glob on ids")
    k.add_argument("--tag", action="append", help="only cases with these tags")
    k.set_defaults(fn=cmd_cases)

    b = sub.add_parser("backends", help="list backends and what they can do")
    b.set_defaults(fn=cmd_backends)

    rp = sub.add_parser("report", help="rebuild report.md/html of a run directory")
    rp.add_argument("run_dir")
    rp.set_defaults(fn=cmd_report)

    sp = sub.add_parser("speed", help="root finders on 2^20 rays at a sphere and a torus ∪ box, in units of the "
                        "closed-form sphere intersection (the backends issue's speed targets)")
    sp.add_argument("--backend", action="append", help="backend ids (default: all available)")
    sp.add_argument("--method", default="hybrid_secant")
    sp.add_argument("--knobs", help='JSON knob dict, e.g. \'{"xtol": 1e-8}\' (default: the method\'s defaults)')
    sp.add_argument("--side", type=int, default=1024, help="rays per image side (default 1024: 2^20 rays)")
    sp.add_argument("--repeats", type=int, default=3)
    sp.add_argument("--threads", type=int, default=1, help="threads per library and worker threads of the numpy/torch "
                    "root-finder drivers (default 1)")
    sp.add_argument("--allocator", choices=("tuned", "default"), default="tuned", help=ALLOCATOR_HELP)
    sp.add_argument("--out", help="write the rows as JSON")
    sp.set_defaults(fn=cmd_speed)

    args = p.parse_args(argv)
    return args.fn(args)


if __name__ == "__main__":
    sys.exit(main())
