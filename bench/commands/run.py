"""``python -m bench run``: run a suite and write results and a report.

    python -m bench run --suite quick [--backend numpy,jax:cpu] [--method sphere_trace] [--case 'sphere.*']
                        [--dtype float64] [--out DIR] [--resume] [--threads 1] [--allocator tuned|default]
                        [--accuracy-only] [--no-claims] [--no-stability] [--budget S] [--timeout S]
                        [--cluster local:N | --scheduler ADDRESS]

The configurations run through :func:`bench.run.runner.run` (in this process, or on a dask
cluster with ``--cluster``/``--scheduler``), then the suite's stability stage, the claims ledger
and the report (:mod:`bench.commands._run_stages`).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ._common import (ALLOCATOR_HELP, DEFAULT_REPORTS, ProgressLines, UsageError, configure_process, error,
                      int_at_least, load_user_cases, make_console, reference_cache_dir, resolve_backends,
                      run_claims_into, seconds, split)
from ._run_options import LIST_OPTIONS, RESUMED_OPTIONS, contradictions, empty_option, restore_run_options, run_options
from ._run_stages import closing_summary, run_stability_into, start_executor

ORDER = 0
HELP = "run a suite and write results and a report"
#: ``--max-time`` when not given (raised to ``--min-time`` when that is larger)
DEFAULT_MAX_TIME_S = 5.0


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--suite", default="quick",
                   help="quick (CI, the showcase), full (every method on 3 cases, sweeps, float32, every workload "
                   "case) or workloads (the mesh, grid and neural cases only, default knobs)")
    p.add_argument("--backend", action="append", help="backend ids, comma-separated or repeated (default: all available)")
    p.add_argument("--method", action="append", help="methods to run, names or globs such as 'volume_*' "
                   "(default: all in the suite)")
    p.add_argument("--case", help="glob(s) on case ids, comma-separated (default: the suite's); the matching cases run "
                   "each method with its whole knob sweep; '*' (the catalog sweep) still leaves out what the suite "
                   "excludes for cost, a glob that names cases runs them too")
    p.add_argument("--cases", action="append", help="your own cases: package.module:attribute (a Case, a list of them, or a function "
                   "returning either), comma-separated; they join the catalog tagged 'user' (reference/user_cases.py)")
    p.add_argument("--dtype", action="append", help="float64 and/or float32 (default: the suite's)")
    p.add_argument("--out", help="output directory (default: reports/<run-id>/)")
    p.add_argument("--min-time", type=seconds, default=None, help="seconds of timed calls per configuration "
                   "(default: the suite's, 0.02 quick, 0.05 full)")
    p.add_argument("--max-time", type=seconds, default=None, help="seconds of timed calls per configuration at most "
                   f"(default {DEFAULT_MAX_TIME_S:g}, or --min-time if larger; ≥ --min-time)")
    p.add_argument("--min-repeats", type=int_at_least(1), default=None, help="timing samples per configuration at least "
                   "(default: the suite's, 3 quick, 5 full)")
    p.add_argument("--timeout", type=seconds, default=120.0, help="hard limit per configuration in seconds; past it the "
                   "configuration is a failed 'timeout' row and the run goes on (default 120, 0: none)")
    p.add_argument("--threads", type=int_at_least(1), default=1, help="threads per library (BLAS/OpenMP, torch, XLA), fixed and "
                   "recorded (default 1)")
    p.add_argument("--allocator", choices=("tuned", "default"), default="tuned", help=ALLOCATOR_HELP)
    p.add_argument("--accuracy-only", action="store_true", help="one call per configuration, no timing samples "
                   "(deterministic, for baselines), each backend with its compile-light driver settings where it "
                   "has them (jax: one compaction level; the same results, recorded with every row)")
    p.add_argument("--resume", action="store_true", help="finish the interrupted run in --out DIR, with the plan "
                   "options it recorded (--suite, --case, --method, --dtype, --backend, --cases, --threads, "
                   "--allocator, --accuracy-only, --no-claims, --no-stability); every case is checked against the content hash "
                   "it was run with (see --rerun-case); the timing-sample options, --budget and --cluster are this session's")
    p.add_argument("--rerun-case", action="append", metavar="GLOB", help="with --resume: run these cases (globs on "
                   "ids, comma-separated) again from scratch when their content changed since the run started (their "
                   "old rows are dropped); without it a changed case refuses the resume, naming it")
    p.add_argument("--rounds", type=int_at_least(1), default=1, help="time the whole plan this many times, round after round, "
                   "and pool the samples (robust run-to-run timing comparisons on a shared machine; default 1)")
    p.add_argument("--budget", type=seconds, default=None, help="wall-clock guard against a hang, in seconds "
                   "(default none: the whole plan runs whatever the machine's speed; 0: none). A run that spends it "
                   "bounds the configuration in flight, records what is left as skipped 'over budget' rows, is marked "
                   "incomplete and exits 1; --resume finishes it")
    p.add_argument("--no-claims", action="store_true", help="do not run the claims ledger at the end")
    p.add_argument("--no-stability", action="store_true", help="do not run the suite's stability stage (every root "
                   "finder × dtype on one case per adversarial ray family, accuracy only, into stability/)")
    p.add_argument("--reference-timeout", type=seconds, default=30.0, help="seconds for one costly reference answer (a "
                   "rendering integral for one case and density; a user case's numerical first hits, which run its "
                   "field: per pass of 4,096 rays); past it that quantity (that case) is skipped with the reason, and not retried in this "
                   "run (default 30, 0: none)")
    p.add_argument("--no-reference-cache", action="store_true", help="recompute costly reference answers (the "
                   "rendering integral, numerical first hits) instead of reusing those kept in the cache directory "
                   "(after changing what a user field reads at call time, e.g. an environment variable or a file)")
    p.add_argument("--cache-dir", help="where compiled kernels (jax, numba) and costly reference answers are kept "
                   "between runs (default: $XDG_CACHE_HOME/isobench, else ~/.cache/isobench; recorded as cache_dir)")
    p.add_argument("--no-cache", action="store_true", help="a cold start: no persistent cache is read or written, "
                   "every kernel is compiled afresh")
    p.add_argument("--cluster", metavar="local:N", help="run the configurations as tasks on a dask LocalCluster of N "
                   "single-threaded worker processes (bench/run/cluster.py; N × --threads ≤ cores unless --accuracy-only); "
                   "results, resume and the report are those of a run in one process, each row records its worker")
    p.add_argument("--scheduler", metavar="ADDRESS", help="run the configurations on an existing dask cluster "
                   "(e.g. tcp://host:8786); its workers need this isobench and, for timing, --nthreads 1, and should "
                   "declare --resources isobench-task=1 (then a worker runs one configuration at a time; its "
                   "scheduler's allowed-failures decides when a configuration that kills its worker fails)")
    p.add_argument("--no-progress", action="store_true", help="no live progress bar and no periodic progress lines "
                   "(stage lines and the summary still print; without it, progress is a live bar on a terminal and "
                   "plain lines when piped)")
    p.set_defaults(run_option_defaults={dest: p.get_default(dest) for dest in RESUMED_OPTIONS})


def run(args) -> int:
    from ..run.rundir import RunLock

    held: list = []  # the run directory's lock and the cluster executor, once taken: closed whatever happens
    refused = False
    try:
        return _run(args, held)
    except UsageError as exc:
        refused = True
        return error(str(exc))
    finally:
        for thing in reversed(held):  # the executor, then the run directory's lock
            if refused and isinstance(thing, RunLock):  # a refused run leaves no new, empty --out behind
                thing.discard()
            else:
                thing.close()


def _check_options(args) -> None:
    """Options that name nothing, a resumed plan's recorded options, contradictions (UsageError)."""
    err = empty_option(args, LIST_OPTIONS)
    if not err and args.resume and args.out:
        err = restore_run_options(args)
    err = err or contradictions(args)  # after the restore: a resumed plan's options count too
    if err:
        raise UsageError(err)


def _suite(args):
    """The suite of ``--suite`` (UsageError naming the known ones)."""
    from ..run.suites import get_suite

    try:
        return get_suite(args.suite)
    except ValueError as exc:
        raise UsageError(f"--suite: {exc}") from None


def _precheck(args) -> None:
    """The options' errors that need neither the case catalog nor a backend object, raised
    before either is built (a suite's tag selection builds the whole catalog, several seconds;
    the backends import their libraries), and before ``--out`` is claimed (a refused run leaves no
    directory behind): ``--out`` not empty (without creating anything:
    :func:`bench.run.rundir.claim_out` checks again under its lock), ``--method`` and ``--dtype``
    names that name nothing (:func:`bench.run.plan.method_names`, the plan checks them again), and
    backend ids that name nothing (:func:`impls.registry.unknown_reason`)."""
    from impls import registry

    from ..run.plan import check_dtypes, method_names
    from ..run.rundir import OutError, require_empty

    if args.out and not args.resume and Path(args.out).is_dir():
        try:
            require_empty(Path(args.out))
        except OutError as exc:
            raise UsageError(str(exc)) from None
    try:
        method_names(split(args.method))
        check_dtypes(split(args.dtype))
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    for spec in split(args.backend) or ():
        why = registry.unknown_reason(spec)
        if why:
            raise UsageError(f"--backend: {why}; `python -m bench backends` lists the backends")


def _select(args, suite):
    """The cases of the options, checked before any backend is imported."""
    from ..run import plan

    err = load_user_cases(args)
    if err:
        raise UsageError(err)
    if args.resume and not args.out:
        raise UsageError("--resume needs --out DIR: the run directory to finish")
    try:
        cases = plan.select_cases(suite, args.case)
    except ValueError as exc:
        raise UsageError(f"--case: {exc}") from None
    if not cases:  # fail fast, before importing any backend
        raise UsageError(f"--case: nothing to run: no case matches {args.case or suite.case_pattern!r}; "
                         "`python -m bench cases` lists the cases")
    return cases


def _backend_ids_known(args) -> bool:
    """Whether every ``--backend`` id names a backend, found without importing any library
    (``impls.registry.unknown_reason``); :func:`_backends` says what is wrong otherwise."""
    from impls import registry

    return all(registry.unknown_reason(spec) is None for spec in split(args.backend) or ())


def _backends(args) -> dict:
    """{id: backend or Unavailable} of ``--backend`` (default: every registered one); a plug-in's
    spec is kept in ``args.specs`` (id → spec) for the run's record and the cluster's workers."""
    args.specs = {}
    from impls import registry

    backends, msg = resolve_backends(split(args.backend) or registry.default_ids(), args.threads, specs=args.specs)
    if msg:
        raise UsageError(msg + "; `python -m bench backends` lists the backends")
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(args.threads)
    for bid, b in backends.items():
        if isinstance(b, registry.Unavailable):
            print(f"backend {bid} unavailable, its rows are skipped: {b.reason}", flush=True)
    return backends


def _policy(args, suite):
    """The :class:`bench.run.timing.TimingPolicy` of the options and the suite's defaults."""
    from ..run.timing import TimingPolicy

    min_time = suite.min_time_s if args.min_time is None else args.min_time
    min_repeats = suite.min_repeats if args.min_repeats is None else args.min_repeats
    max_time = max(DEFAULT_MAX_TIME_S, min_time) if args.max_time is None else args.max_time
    if min_time > max_time:  # a suite's --min-time above an explicit --max-time
        raise UsageError(f"--max-time {max_time:g}: below the suite's --min-time {min_time:g}; give --max-time ≥ "
                         f"{min_time:g} or a smaller --min-time")
    try:
        return TimingPolicy(min_repeats=min_repeats, min_time_s=min_time, timeout_s=args.timeout,
                            accuracy_only=args.accuracy_only, max_time_s=max_time)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def _run(args, held: list) -> int:
    from ..run import plan
    from ..run.rundir import claim_out
    from ..run.supervise import note_out

    _check_options(args)
    cache_record = configure_process(args)
    console = make_console()
    suite = _suite(args)
    policy = _policy(args, suite)
    _precheck(args)
    cases = _select(args, suite)
    run_id = plan.new_run_id()
    # absolute: a backend's os.chdir must not move where the run writes (or its in-flight note)
    out = (Path(args.out) if args.out else DEFAULT_REPORTS / run_id).absolute()
    try:  # this process is the run directory's one writer from here on (bench.run.rundir)
        held.append(claim_out(out, resume=args.resume))
    except ValueError as exc:  # OutError, LockHeld
        raise UsageError(str(exc)) from None
    note_out(out)  # for the supervising process, which resumes the run if this one dies (bench.run.supervise)
    live = console.is_terminal and not args.no_progress
    lines = ProgressLines(periodic=not live and not args.no_progress)
    # without a cluster, the second process starts now and loads its libraries while this one
    # loads its own (3–4 s each on 2 cores: one core idled through them when it started after)
    early = not (args.cluster or args.scheduler) and _backend_ids_known(args)
    side = _start_side_stages(args, suite, out, None, lines) if early else None
    held += [side] if side else []
    backends = _backends(args)
    budget = suite.budget_s if args.budget is None else (args.budget or None)
    executor, msg = start_executor(args, lines)
    if msg:
        raise UsageError(msg)
    held += [executor] if executor else []
    if not early:
        side = _start_side_stages(args, suite, out, executor, lines)
        held += [side] if side else []
    lines.line(f"run {'(resumed) ' if args.resume else ''}suite {suite.name}: {len(cases)} cases, backends "
               f"{', '.join(backends)}; budget {'none' if budget is None else f'{budget:g} s'}; out {out}")
    options = _run_options_of(args, suite, backends, policy, budget, run_id, executor,
                              {"threads": str(args.threads), "run_options": run_options(args, list(args.specs.values())),
                               **cache_record}, side)
    df = _execute(suite, backends, out, options, console, lines, live)
    return _finish(args, suite, backends, out, df, console, lines, executor, side)


def _run_options_of(args, suite, backends, policy, budget, run_id, executor, env_extra, side=None):
    """The runner's :class:`bench.run.runner.RunOptions` of the command's options; ``side``: the
    second process, which joins the configurations after its stages where it shares the plan."""
    from ..run.runner import RunOptions

    return RunOptions(case_pattern=args.case, methods=split(args.method), dtypes=split(args.dtype), policy=policy,
                      run_id=run_id, resume=args.resume, env_extra=env_extra, budget_s=budget, rounds=args.rounds,
                      reference_cache_dir=reference_cache_dir(args), reference_timeout_s=args.reference_timeout,
                      executor=executor, rerun_cases=split(args.rerun_case),
                      share=None if side is None or side.share is None else (side.share, side.alive, side.kill))


def _execute(suite, backends, out: Path, options, console, lines: ProgressLines, live: bool):
    """The configurations, with a live bar on a terminal and progress lines otherwise."""
    from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                               TimeRemainingColumn)

    from ..run import runner

    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  TimeRemainingColumn(), console=console, disable=not live) as prog:
        task = prog.add_task("planning", total=None)

        def progress(i, n, what, counts):
            lines(i, n, what, counts)
            prog.update(task, total=n, completed=i, description=what[:70])

        try:
            return runner.run(suite, backends, out, options, progress=progress)
        except ValueError as exc:
            raise UsageError(str(exc)) from None


def _stages(args, suite) -> tuple[str, ...]:
    """The accuracy-only stages this run has after its configurations: "stability" (the suite's
    stability stage, unless left out or the plan is narrowed), "claims" (unless --no-claims)."""
    stability = suite.stability and not (args.no_stability or args.case or args.method or args.dtype)
    return (("stability",) if stability else ()) + (() if args.no_claims else ("claims",))


def _start_side_stages(args, suite, out: Path, executor, lines: ProgressLines):
    """The stages in a second process, started now (:mod:`bench.commands._side_stages`), or None
    where they run after the configurations (no core for them, a cluster executor, none asked)."""
    from ._side_stages import SideStages, concurrent_ok

    stages = _stages(args, suite)
    if not stages or not concurrent_ok(args, executor):
        return None
    from ..run.sharing import PlanShare

    share = PlanShare() if args.rounds == 1 else None  # --rounds re-times every configuration here
    lines.line(f"{' and '.join(stages)}: in a second process, beside the configurations (accuracy only)"
               + ("; then it takes configurations too" if share else ""))
    child_args = argparse.Namespace(**{k: v for k, v in vars(args).items() if k != "fn"})
    return SideStages(stages, (child_args, str(out), suite.stability if "stability" in stages else None,
                               "claims" in stages, suite.name == "quick"), share=share).start()


def _finish(args, suite, backends, out: Path, df, console, lines: ProgressLines, executor, side=None) -> int:
    """The stability stage and the claims (unless left out; waited for when a second process runs
    them), the report, the closing summary."""
    from ..report import build as report
    from ..run.results import write_json
    from ..run.suites import get_suite
    from ._side_stages import CONCURRENT, SEQUENTIAL

    env = json.loads((out / "environment.json").read_text())
    stages = _stages(args, suite)
    if side is not None:
        lines.line(f"waiting for {' and '.join(stages)} (second process)")
        env.update({stage: note or "ran" for stage, note in side.wait().items()})
        env["side_stages"] = CONCURRENT
        write_json(out / "environment.json", env)
    elif stages:
        env["side_stages"] = SEQUENTIAL
    if side is None and "stability" in stages:
        lines.line(f"stability: root finders × dtypes on one case per adversarial ray family ({suite.stability})")
        note = run_stability_into(out, get_suite(suite.stability), backends, args, console, executor)
        env["stability"] = note or "ran"
        write_json(out / "environment.json", env)
    if side is None and "claims" in stages:
        lines.line("claims: checking the lecture's claims")
        note = run_claims_into(out, quick=suite.name == "quick", console=console,
                               reference_dir=reference_cache_dir(args))
        env["claims"] = note or "ran"
        write_json(out / "environment.json", env)
    lines.line("report: writing report.md and report.html")
    fs = report.build(df, env, out)
    code, errors = closing_summary(df, env, out, lines, fs)
    nominal = {"quick": 240.0, "full": 900.0}.get(suite.name)
    if nominal and float(env.get("elapsed_s", 0)) > nominal:
        print(f"note: the {suite.name} suite took {env.get('elapsed_s')} s, more than its nominal {nominal:g} s "
              "(a loaded machine, or select less with --case/--method)", flush=True)
    for e in errors:
        error(e)
    return code
