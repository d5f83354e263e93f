"""``python -m bench``: run suites, compare runs, list cases and backends.

    python -m bench run --suite quick [--backend numpy,jax:cpu] [--method sphere_trace] [--case 'sphere.*']
                        [--dtype float64] [--out DIR] [--resume] [--threads 1] [--allocator tuned|default]
                        [--accuracy-only] [--no-claims] [--no-stability] [--budget S] [--timeout S]
                        [--cluster local:N | --scheduler ADDRESS]
    python -m bench spread RUN_DIR [--workers 1 2 64] [--overhead-s S] [--central-s S]
    python -m bench speed [--backend numpy,torch,jax] [--method hybrid_secant] [--repeats 3] [--threads 1]
                          [--allocator tuned|default] [--no-peers] [--volume [--samples 256]] [--mesh]
    python -m bench edges [--backend warp,mitsuba] [--mesh torus,fin] [--offsets 1e-2,1e-5,1e-9] [--out DIR]
    python -m bench sampling [--case sphere.camera.64x64,torus.camera.32x32] [--targets 1e-2,1e-3,1e-4]
    python -m bench compare BASE NEW [--timing] [--factor 1.1] [--allow-missing] [--min-comparable 1]
    python -m bench claims [--out DIR] [--full] [--only ID ...]
    python -m bench cases [--tag grazing]
    python -m bench backends
    python -m bench report RUN_DIR

Exit codes: 0 success; 1 the command ran but its answer is "no": a regression or an incomplete
comparison (``compare``), a run that is incomplete (its ``--budget`` ran out) or in which no
configuration ran (``run``), a claims check that failed (``claims``); 2 a usage error (a bad
argument, an unknown backend, an ``--out`` that is not new or empty, a run directory another
process is writing, a path that cannot be created), reported as one line
``error: …`` on stderr naming the argument and the fix.  Progress and summaries go to stdout,
as lines when it is not a terminal (a live bar when it is).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from .environment import ROOT

DEFAULT_REPORTS = ROOT / "reports"
#: ``bench run --max-time`` when not given (raised to ``--min-time`` when that is larger)
DEFAULT_MAX_TIME_S = 5.0

def _error(message: str, code: int = 2) -> int:
    """One line on stderr, ``error: …`` (argparse's style and exit code 2 for usage errors)."""
    print(f"error: {message}", file=sys.stderr, flush=True)
    return code


def _int_at_least(low: int):
    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        if v < low:
            raise argparse.ArgumentTypeError(f"must be ≥ {low}, got {v}")
        return v

    return parse


def _seconds(text: str) -> float:
    """A finite number of seconds ≥ 0."""
    import math

    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not (math.isfinite(v) and v >= 0):
        raise argparse.ArgumentTypeError(f"must be a finite number of seconds ≥ 0, got {text}")
    return v


def _share(text: str) -> float:
    """A share in (0, 1] (``--min-comparable``)."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number; give a share in (0, 1], e.g. 0.9") from None
    if not 0 < v <= 1:
        raise argparse.ArgumentTypeError(f"must be a share in (0, 1] (1: every row of BASE), got {text}")
    return v


def _json_dict(text: str) -> dict:
    try:
        v = json.loads(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"not valid JSON ({exc}); write e.g. '{{\"xtol\": 1e-8}}'") from None
    if not isinstance(v, dict):
        raise argparse.ArgumentTypeError(f"must be a JSON object of knob → value, got {type(v).__name__}")
    return v


def _resolve_backends(ids: list[str], threads: int, flag: str = "--backend"):
    """{id: backend or Unavailable}, each loop driver given ``threads`` worker threads, or an
    error message when an id names nothing (a typo)."""
    from impls import registry

    from .environment import configure_driver

    backends = {bid: registry.resolve(bid) for bid in ids}
    for b in backends.values():
        if not isinstance(b, registry.Unavailable):
            configure_driver(b, threads)
    unknown = [b for b in backends.values() if isinstance(b, registry.Unavailable) and b.unknown]
    if unknown:
        return None, f"{flag}: " + "; ".join(b.reason for b in unknown)
    return backends, ""


def _write_out_file(out: str, write) -> str:
    """``write(path)`` for a file-valued ``--out``; "" or the error message naming ``--out`` (a
    directory there, a parent that is a file, no permission)."""
    path = Path(out)
    if path.is_dir():
        return f"--out: {path} is a directory; pass a file name"
    try:
        write(path)
    except OSError as exc:
        return f"--out: cannot write {path}: {exc.strerror or exc}; pass a file in a directory you can write"
    return ""


def _split(values: list[str] | None) -> list[str] | None:
    if not values:
        return None
    return [v for item in values for v in item.split(",") if v]


def _console():
    from rich.console import Console

    import os

    return Console(highlight=False, width=None if os.isatty(1) else 200)


def run_claims_into(out: Path, *, quick: bool, console, only: list[str] | None = None) -> str:
    """Call the claims ledger (``bench.claims.run_claims``, the claims ``only`` or all) into
    ``out``; never raises.  Returns a one-line note for the report and the console ("" when it
    worked)."""
    try:
        from .claims import run_claims

        df = run_claims(out, quick=quick, only=only)
        n = 0 if df is None else len(df)
        console.print(f"claims: {n} checked, ledger in {out / 'claims.csv'}")
        return ""
    except Exception as exc:  # the ledger is a section of the report, never a reason to crash
        note = f"claims failed: {type(exc).__name__}: {exc}"
        console.print(f"[yellow]{note}[/]")
        return note


class _ProgressLines:
    """Progress as plain lines, whatever stdout is (piped, CI, a terminal): one per stage, and
    during the configurations one every ``step`` of them (10 % of the plan or 20, the smaller) and
    at least every ``every_s`` seconds, each with done/total, ok/skipped/failed and the elapsed
    time.  ``periodic=False``: stage lines only (the live bar shows the rest, or --no-progress)."""

    def __init__(self, periodic: bool = True, every_s: float = 30.0):
        import time

        self._clock = time.monotonic
        self.t0 = self._clock()
        self.periodic, self.every_s = periodic, every_s
        self._next, self._last, self.planned = 0, self.t0, False

    def line(self, text: str) -> None:
        print(f"[{self._clock() - self.t0:7.1f} s] {text}", flush=True)

    def __call__(self, i: int, n: int, what: str, counts: dict) -> None:
        if not self.planned:
            self.planned = True
            self.line(f"plan: {n} configurations" + (f", {i} kept from the interrupted run" if i else ""))
            step = max(1, min(20, -(-n // 10)))
            self._next = (i // step + 1) * step
            self._step = step
            return
        now = self._clock()
        if not self.periodic or (i < self._next and now - self._last < self.every_s and i < n):
            return
        while self._next <= i:
            self._next += self._step
        self._last = now
        pct = 100 * i // max(n, 1)
        self.line(f"configurations {i}/{n} ({pct}%): {counts.get('ok', 0)} ok, {counts.get('skipped', 0)} skipped, "
                  f"{counts.get('failed', 0)} failed" + ("" if what == "done" else f"; last: {what[6:86]}"
                                                          if what.startswith("last:") else f"; next: {what[:80]}"))


def _first_screen_lines(df, env: dict, out: Path) -> list[str]:
    """The report's answers in a few lines: which to pick at 1e-8, the stability scoreboard, the
    claims' verdict counts (:func:`bench.summary.first_screen`); nothing if they cannot be made."""
    from . import report, stability, summary

    try:
        cells, _ = report.stability_section(df, out)
        board = stability.scoreboard_lines(stability.scoreboard(cells)) if len(cells) else []
        fs = summary.first_screen(df, env, claims=report.read_claims(out), scoreboard=board)
        text = summary.terminal_text(fs).splitlines()[1:]  # the first line repeats the counts above
        return [t[:160] for t in text]
    except Exception as exc:  # the summary must never cost the run its exit code
        return [f"(summary unavailable: {type(exc).__name__}: {exc})"]


def _summary(df, env: dict, out: Path, lines: _ProgressLines) -> tuple[int, list[str]]:
    """The closing lines (counts, failures, incompleteness, report path) and the exit code:
    0, or 1 when the run is incomplete (its --budget ran out) or no configuration ran."""
    from . import report

    configs = report.config_outcomes(df)
    n = {o: int((configs["outcome"] == o).sum()) for o in ("ok", "skipped", "failed")}
    from .results import OVER_BUDGET

    n_over = int(configs["reason"].fillna("").astype(str).str.startswith(OVER_BUDGET).sum())
    said = [f"{n['ok']} configurations ran, {n['skipped']} skipped"
            + (f" ({n_over} of them over the time budget)" if n_over else "")
            + f", {n['failed']} failed in {env.get('elapsed_s', '?')} s"]
    failed = configs[configs["outcome"] == "failed"]
    if len(failed):
        by_reason = failed.groupby(failed["reason"].fillna("").astype(str).str.slice(0, 120), sort=False)
        for reason, g in list(by_reason)[:5]:
            first = g.iloc[0]
            said.append(f"  failed ×{len(g)}: {first['backend']} {first['method']} on {first['case_id']}"
                        f"{' and others' if len(g) > 1 else ''}: {reason}")
        if by_reason.ngroups > 5:
            said.append(f"  … {by_reason.ngroups - 5} more kinds of failure: see the report")
    said += _first_screen_lines(df, env, out)
    said.append(f"report: {out / 'report.html'}")
    for text in said:
        print(text, flush=True)
    errors = []
    if env.get("complete") != "true":
        errors.append(f"the run is INCOMPLETE: {env.get('incomplete_reason', 'unknown reason')} "
                      f"(python -m bench run --resume --out {out})")
    if n["ok"] == 0:
        errors.append(f"no configuration ran ({n['failed']} failed, {n['skipped']} skipped): nothing was measured; "
                      "see the reasons above and in the report")
    return (1 if errors else 0), errors


def run_stability_into(out: Path, suite, backends: dict, args, console, executor=None) -> str:
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
                       env_extra={"threads": str(args.threads)}, executor=executor)
    except Exception as exc:  # the stage must not cost the run its report
        note = f"stability stage failed: {type(exc).__name__}: {exc}"
        console.print(f"[red]{note}[/]")
        return note
    console.print(f"stability: {len(df)} rows in {time.monotonic() - started:.1f} s, in {out / STABILITY_DIR}")
    return ""


def _start_executor(args, lines):
    """The :class:`bench.cluster.ClusterExecutor` of ``--cluster``/``--scheduler`` (started), None
    without them, or an error message."""
    if not (args.cluster or args.scheduler):
        return None, ""
    if args.cluster and args.scheduler:
        return None, "--cluster and --scheduler: give one (local:N starts a cluster, --scheduler uses an existing one)"
    try:
        from .cluster import ClusterExecutor, parse_local
    except ImportError as exc:
        return None, (f"--cluster/--scheduler need dask.distributed ({exc}); install it with "
                      "pip install -c constraints.txt -e '.[cluster]'")
    try:
        executor = ClusterExecutor(local=parse_local(args.cluster) if args.cluster else None, scheduler=args.scheduler,
                                   threads=args.threads, allocator=args.allocator,
                                   case_specs=tuple(_split(args.cases) or ()), accuracy_only=args.accuracy_only)
        executor.start()
    except ValueError as exc:
        return None, str(exc)
    rec = executor.env_record()
    lines.line(f"cluster: {rec['cluster']} ({executor._capacity(fresh=True)} worker threads, started in "
               f"{rec['cluster.start_s']} s; {float(rec.get('cluster.central_s', 'nan')) * 1e3:.1f} ms central cost "
               "per task)")
    return executor, ""


def cmd_run(args) -> int:
    held: list = []  # the run directory's lock and the cluster executor, once taken: closed whatever happens
    try:
        return _cmd_run(args, held)
    finally:
        for thing in reversed(held):  # the executor, then the run directory's lock
            thing.close()


#: ``bench run`` options that define a run's plan and how its rows are measured: recorded in
#: environment.json (``run_options``) and restored by ``--resume``, so a resumed run finishes the
#: plan it started, its stages (claims, stability) included (``--case '*'`` stays the catalog sweep without retyping it).  The timing-sample
#: options (--min-time, --min-repeats, --max-time, --timeout, --rounds), --budget, --cluster and
#: --scheduler are per session: a resume may change them, as the budget hint says.
RESUMED_OPTIONS = ("suite", "case", "method", "dtype", "backend", "cases", "threads", "allocator", "accuracy_only",
                   "no_claims", "no_stability")


def _flag(dest: str) -> str:
    return "--" + dest.replace("_", "-")


def _shown(dest: str, value) -> str:
    """An option as the user would type it: ``--case 'box.*'``, ``--dtype 'float32,float64'``, ``no --case``."""
    if value is None or value is False:
        return "no " + _flag(dest)
    if value is True:
        return _flag(dest)
    return f"{_flag(dest)} {','.join(value) if isinstance(value, list) else value!r}"


def _restore_run_options(args) -> str | None:
    """With ``--resume``: set ``args``' :data:`RESUMED_OPTIONS` to those recorded by the run in
    ``--out``; an option given now that differs from the recorded one (and from its default) is an
    error naming it, not a silently different plan.  A run recorded before options were (no
    ``run_options``) resumes with the options given now, with a warning.  Returns an error message
    or None."""
    env_path = Path(args.out) / "environment.json"
    try:
        recorded = json.loads(json.loads(env_path.read_text()).get("run_options", "null"))
    except (OSError, ValueError):
        return None  # the runner reports a missing or broken environment.json with the fix
    if recorded is None:
        print(f"warning: {env_path} records no run options (a run from an older isobench): resuming with the "
              "--suite/--case/--method/--dtype/--backend given now; give the ones it started with",
              file=sys.stderr, flush=True)
        return None
    defaults = args.run_option_defaults
    for dest in RESUMED_OPTIONS:
        given, then = _normal(dest, getattr(args, dest)), _normal(dest, recorded.get(dest, defaults[dest]))
        if given != _normal(dest, defaults[dest]) and given != then:
            return (f"{_flag(dest)}: the run in {args.out} was started with {_shown(dest, then)} "
                    f"(given now: {_shown(dest, given)}); "
                    f"--resume finishes the plan it started: drop {_flag(dest)} (the recorded value is used), "
                    "or start a new run with another --out")
        setattr(args, dest, then)
    return None


def _normal(dest: str, value):
    """Repeated and comma-separated list options as one list (``--dtype a,b`` = ``--dtype a --dtype b``)."""
    return _split(value) if dest in ("method", "dtype", "backend", "cases") else value


def _run_options(args, backend_ids) -> str:
    """The JSON of :data:`RESUMED_OPTIONS` as this run uses them (backends resolved to ids)."""
    rec = {dest: _normal(dest, getattr(args, dest)) for dest in RESUMED_OPTIONS}
    rec["backend"] = list(backend_ids)
    return json.dumps(rec, sort_keys=True)


#: ``bench run`` options given as lists or globs: given, they must name something
LIST_OPTIONS = ("case", "method", "dtype", "backend", "cases", "rerun_case")


def _empty_option(args, dests) -> str | None:
    """An error for the first of ``dests`` given but empty (``--method ''`` would otherwise mean
    "all"), or None."""
    for dest in dests:
        value = getattr(args, dest, None)
        if value is None:
            continue
        items = _split(value) if isinstance(value, list) else [v for v in str(value).split(",") if v.strip()]
        if not items:
            shown = ",".join(value) if isinstance(value, list) else value
            return (f"{_flag(dest)}: given empty ({shown!r}); name what you mean (`python -m bench cases` / "
                    f"`backends` list them), or leave {_flag(dest)} out for the default")
    return None


def _contradictions(args) -> str | None:
    """An error naming two ``bench run`` options that cannot both hold, or None."""
    if args.min_time is not None and args.max_time is not None and args.min_time > args.max_time:
        return (f"--min-time {args.min_time:g} and --max-time {args.max_time:g}: at least {args.min_time:g} s of "
                f"timed calls cannot fit in at most {args.max_time:g} s; give --min-time ≤ --max-time")
    if args.rounds > 1 and args.accuracy_only:
        return (f"--rounds {args.rounds} and --accuracy-only: an accuracy-only run takes no timing samples to pool "
                "over rounds; drop one")
    if args.rerun_case and not args.resume:
        return "--rerun-case without --resume: a new run runs every case anyway; add --resume --out DIR, or drop it"
    return None


def _configure_caches(args) -> dict[str, str]:
    """Set up the persistent caches (``--cache-dir``, ``--no-cache``) before any backend is
    imported (:func:`bench.environment.configure_caches`); returns the environment record."""
    from .environment import configure_caches, default_cache_dir

    if args.no_cache:
        return configure_caches(None)
    return configure_caches(Path(args.cache_dir) if args.cache_dir else default_cache_dir())


def _reference_cache(args) -> Path | None:
    """Where a run keeps costly reference answers: ``<cache dir>/reference`` (None with
    ``--no-cache`` or ``--no-reference-cache``)."""
    from impls.cache import subdir

    return None if args.no_reference_cache else subdir("reference")


def _cmd_run(args, held: list) -> int:
    from .environment import configure_threads

    err = _empty_option(args, LIST_OPTIONS)
    if err:
        return _error(err)
    if args.resume and args.out:
        err = _restore_run_options(args)
        if err:
            return _error(err)
    err = _contradictions(args)  # after the restore: a resumed plan's options count too
    if err:
        return _error(err)

    configure_threads(args.threads)  # before any array library is imported
    cache_record = _configure_caches(args)  # before any backend is imported
    if args.allocator == "tuned":
        from .environment import tune_allocator

        tune_allocator()
    from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                               TimeRemainingColumn)

    from . import report, runner
    from .results import write_json
    from .suites import get_suite
    from .timing import TimingPolicy

    console = _console()
    try:
        suite = get_suite(args.suite)
    except ValueError as exc:
        return _error(f"--suite: {exc}")
    err = _load_user_cases(args)
    if err:
        return _error(err)
    if args.resume and not args.out:
        return _error("--resume needs --out DIR: the run directory to finish")
    try:
        cases = runner.select_cases(suite, args.case)
    except ValueError as exc:
        return _error(f"--case: {exc}")
    if not cases:  # fail fast, before importing any backend
        return _error(f"--case: nothing to run: no case matches {args.case or suite.case_pattern!r}; "
                      "`python -m bench cases` lists the cases")
    run_id = runner.new_run_id()
    out = Path(args.out) if args.out else DEFAULT_REPORTS / run_id
    from .rundir import claim_out

    try:  # this process is the run directory's one writer from here on (bench.rundir)
        held.append(claim_out(out, resume=args.resume))
    except ValueError as exc:  # OutError, LockHeld
        return _error(str(exc))
    from impls import registry

    ids = _split(args.backend) or registry.default_ids()
    backends, msg = _resolve_backends(ids, args.threads)
    if msg:
        return _error(msg + "; `python -m bench backends` lists the backends")
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(args.threads)
    for bid, b in backends.items():
        if isinstance(b, registry.Unavailable):
            print(f"backend {bid} unavailable, its rows are skipped: {b.reason}", flush=True)
    try:
        min_time = suite.min_time_s if args.min_time is None else args.min_time
        min_repeats = suite.min_repeats if args.min_repeats is None else args.min_repeats
        max_time = max(DEFAULT_MAX_TIME_S, min_time) if args.max_time is None else args.max_time
        if min_time > max_time:  # a suite's --min-time above an explicit --max-time
            return _error(f"--max-time {max_time:g}: below the suite's --min-time {min_time:g}; give --max-time ≥ "
                          f"{min_time:g} or a smaller --min-time")
        policy = TimingPolicy(min_repeats=min_repeats, min_time_s=min_time, timeout_s=args.timeout,
                              accuracy_only=args.accuracy_only, max_time_s=max_time)
    except ValueError as exc:
        return _error(str(exc))
    budget = suite.budget_s if args.budget is None else (args.budget or None)
    live = console.is_terminal and not args.no_progress
    lines = _ProgressLines(periodic=not live and not args.no_progress)
    executor, msg = _start_executor(args, lines)
    if msg:
        return _error(msg)
    held += [executor] if executor else []
    lines.line(f"run {'(resumed) ' if args.resume else ''}suite {suite.name}: {len(cases)} cases, backends "
               f"{', '.join(backends)}; budget {'none' if budget is None else f'{budget:g} s'}; out {out}")
    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  TimeRemainingColumn(), console=console, disable=not live) as prog:
        task = prog.add_task("planning", total=None)

        def progress(i, n, what, counts):
            lines(i, n, what, counts)
            prog.update(task, total=n, completed=i, description=what[:70])

        try:
            df = runner.run(suite, backends, out, case_pattern=args.case, methods=_split(args.method),
                            dtypes=_split(args.dtype), policy=policy, run_id=run_id, progress=progress,
                            resume=args.resume, env_extra={"threads": str(args.threads),
                                                           "run_options": _run_options(args, backends),
                                                           **cache_record},
                            budget_s=budget,
                            rounds=args.rounds, reference_cache_dir=_reference_cache(args),
                            reference_timeout_s=args.reference_timeout,
                            executor=executor, rerun_cases=_split(args.rerun_case))
        except ValueError as exc:
            return _error(str(exc))
    env = json.loads((out / "environment.json").read_text())
    if suite.stability and not (args.no_stability or args.case or args.method or args.dtype):
        lines.line(f"stability: root finders × dtypes on one case per adversarial ray family ({suite.stability})")
        note = run_stability_into(out, get_suite(suite.stability), backends, args, console, executor)
        env["stability"] = note or "ran"
        write_json(out / "environment.json", env)
    if not args.no_claims:
        lines.line("claims: checking the lecture's claims")
        note = run_claims_into(out, quick=suite.name == "quick", console=console)
        env["claims"] = note or "ran"
        write_json(out / "environment.json", env)
    lines.line("report: writing report.md and report.html")
    report.build(df, env, out)
    code, errors = _summary(df, env, out, lines)
    nominal = {"quick": 240.0, "full": 900.0}.get(suite.name)
    if nominal and float(env.get("elapsed_s", 0)) > nominal:
        print(f"note: the {suite.name} suite took {env.get('elapsed_s')} s, more than its nominal {nominal:g} s "
              "(a loaded machine, or select less with --case/--method)", flush=True)
    for e in errors:
        _error(e)
    return code


def _run_env(path: str) -> dict | None:
    """The environment.json of the run a results path belongs to (a run directory, or the folder
    of a results file), or None when there is none or it cannot be read."""
    p = Path(path)
    p = p if p.is_dir() else p.parent
    try:
        env = json.loads((p / "environment.json").read_text())
        return env if isinstance(env, dict) else None
    except (OSError, ValueError):
        return None


def _incomplete(name: str, df, env: dict | None) -> str:
    """Why a side of a comparison is not a whole run ('' when it is)."""
    from .results import OVER_BUDGET

    over = int(df["reason"].fillna("").astype(str).str.startswith(OVER_BUDGET).sum()) if "reason" in df else 0
    if env is not None and str(env.get("complete", "true")) != "true":
        return f"{name} is an incomplete run: {env.get('incomplete_reason', 'complete=false in environment.json')}"
    if over:
        return f"{name} has {over} rows not measured ({OVER_BUDGET})"
    return ""


def cmd_compare(args) -> int:
    import pandas as pd

    from . import compare as cmp
    from .results import read_results, write_text

    try:
        base, new = read_results(args.base), read_results(args.new)
    except FileNotFoundError as exc:
        return _error(f"BASE/NEW: {exc}")
    except ValueError as exc:
        return _error(f"BASE/NEW: {exc}; pass two run directories (or their results.parquet/.csv)")
    eb, en = _run_env(args.base), _run_env(args.new)
    from .environment import machine_key

    # each row's machine: its own key (a cluster run's rows record their worker's), else its run's
    for df, env in ((base, eb), (new, en)):
        own = df["machine_key"].fillna("").astype(str) if "machine_key" in df else None
        if env is not None:
            df["machine_key"] = machine_key(env) if own is None else own.where(own != "", machine_key(env))
    try:
        res = cmp.compare(base, new, factor=args.factor, alpha=args.alpha, rtol=args.rtol, atol_eps=args.atol_eps,
                          same_machine=True)  # the rows' machine keys decide (same_row_machine)
    except ValueError as exc:
        return _error(str(exc))
    console = _console()
    counts = {col: res[col].value_counts().to_dict() for col in ("accuracy", "timing")}
    worse = res[(res["accuracy"] == "worse") | ((res["timing"] == "worse") & args.timing)]
    if args.out:
        err = _write_out_file(args.out, lambda path: write_text(path, res.to_csv(index=False)))
        if err:
            return _error(err)
    if len(worse):
        from rich.markup import escape

        cols = [c for c in ["case_id", "backend", "dtype", "method", "knob", "quantity", "accuracy", "error_base",
                            "error_new", "timing", "time_ratio", "p_value", "note"] if c in worse.columns]
        console.print(escape(worse[cols].to_string(index=False)))
    console.print(f"accuracy: {counts['accuracy']}")
    differ = int((res.get("note", pd.Series(dtype=str)).fillna("") == "timing measured on different machines").sum())
    console.print(f"timing:   {counts['timing']}" + (f" ({differ} rows measured on different machines: timing not "
                                                      "compared)" if differ else ""))
    # a comparison gates only what it compares: a NEW side that lost rows or did not finish, or
    # a BASE that did not, is a failure, never a pass on fewer rows
    problems = [p for p in (_incomplete("NEW", new, en), _incomplete("BASE", base, eb)) if p]
    missing = res[res["accuracy"] == "missing"]
    if len(missing) and not args.allow_missing:
        ex = missing.iloc[0]
        problems.append(f"{len(missing)} rows of BASE are missing in NEW (e.g. {ex['case_id']} {ex['backend']} "
                        f"{ex['method']} {ex['knob']}): a truncated or partial run? Compare whole runs, or pass "
                        "--allow-missing to compare only the rows NEW has")
    compared, gated = cmp.coverage(res, allow_missing=args.allow_missing)
    console.print(f"compared: {compared} of {gated} rows of BASE")
    short = cmp.coverage_problem(res, args.min_comparable, allow_missing=args.allow_missing)
    if short:
        problems.append(short)
    if len(worse):
        console.print(f"[red]{len(worse)} regression(s)[/]")
    for p in problems:
        _error(p, 1)
    if len(worse) or problems:
        return 1
    console.print("no regression")
    return 0


def cmd_claims(args) -> int:
    """Check the lecture's claims (all, or ``--only`` these ids; ``--full``: the full grids) into
    ``--out``: ``claims.csv``, one ``claim_<id>.png`` each, ``claims.md`` (the ledger as Markdown)
    and the report; a one-line-per-claim summary on stdout."""
    from .results import write_atomic, write_json
    from .runner import new_run_id
    from .environment import collect

    if args.only:
        from .claims import claim_ids

        known = claim_ids()
        unknown = [i for i in args.only if i not in known]
        if unknown:
            return _error(f"--only: unknown claim id(s) {', '.join(unknown)}; known ids are {', '.join(known)}")
    from .rundir import RunLock, make_dir

    out = Path(args.out) if args.out else DEFAULT_REPORTS / ("claims-" + new_run_id())
    try:  # created, and this process's alone until it exits (a run directory has one writer)
        RunLock(make_dir(out)).acquire()
    except ValueError as exc:
        return _error(str(exc))
    except OSError as exc:
        return _error(f"--out: cannot lock {out}: {exc.strerror or exc}; pass a directory you can write")
    held = [n for n in ("claims.csv", "claims.md") if (out / n).exists()]
    if held:
        return _error(f"--out: {out} already holds {', '.join(held)}; results are never overwritten. Pass another --out")
    console = _console()
    note = run_claims_into(out, quick=not args.full, console=console, only=args.only)
    if not (out / "environment.json").exists():
        write_json(out / "environment.json", {**collect(), "run_id": out.name, "suite": "claims"})
    if (out / "claims.csv").exists():
        from .claims.summary import markdown_section, terminal_summary
        from .report import build_from_dir, read_claims

        claims = read_claims(out)
        md = markdown_section(claims)
        write_atomic(out / "claims.md", lambda p: Path(p).write_text(md, encoding="utf-8"))
        build_from_dir(out)
        console.print(terminal_summary(claims), markup=False)
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
        from .results import read_results, write_atomic

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


def _load_user_cases(args) -> str | None:
    """Register the cases of ``--cases`` specs and of the ``isobench.cases`` entry points; an
    error message for a bad spec (a broken entry point is a printed warning, not fatal)."""
    from reference import user_cases

    _, errors = user_cases.load_entry_points()
    for e in errors:
        print(f"warning: a case plug-in could not be loaded: {e}", file=sys.stderr, flush=True)
    for spec in _split(getattr(args, "cases", None)) or []:
        try:
            user_cases.load(spec)
        except (ValueError, TypeError) as exc:
            return str(exc)
    return None


def cmd_cases(args) -> int:
    from reference import catalog

    err = _load_user_cases(args)
    if err:
        return _error(err)

    tags = set(_split(args.tag) or [])
    try:
        found = catalog(args.case, tags)
    except ValueError as exc:
        return _error(f"--case/--tag: {exc}")
    if not found:
        known = sorted({t for c in catalog() for t in c.tags})
        what = " and ".join(x for x in (f"--case {args.case!r}" if args.case else "",
                                         f"--tag {','.join(sorted(tags))}" if tags else "") if x) or "the catalog"
        return _error(f"{what}: no case matches; known tags: {', '.join(known)} (`python -m bench cases` lists all)")
    for c in found:
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

    run_dir = Path(args.run_dir)
    if not run_dir.is_dir():
        return _error(f"RUN_DIR: {run_dir} is not a directory; pass the --out directory of a `bench run`")
    if not (run_dir / "environment.json").exists():
        return _error(f"RUN_DIR: {run_dir} holds no environment.json, so it is not a run directory; pass the --out "
                      "directory of a `bench run` or `bench claims`")
    try:
        build_from_dir(run_dir)
    except ValueError as exc:  # a corrupt results file or environment.json (read_results names the file)
        return _error(f"RUN_DIR: {exc}")
    print(run_dir / "report.html")
    return 0


def cmd_spread(args) -> int:
    from . import spread

    run_dir = Path(args.run_dir)
    if not (run_dir / "environment.json").exists():
        return _error(f"RUN_DIR: {run_dir} holds no environment.json; pass the --out directory of a `bench run`")
    try:
        print(spread.text(run_dir, tuple(args.workers or spread.WORKERS), args.overhead_s, args.central_s))
    except (ValueError, FileNotFoundError) as exc:
        return _error(f"RUN_DIR: {exc}")
    return 0


def cmd_extract(args) -> int:
    from reference.cases import catalog

    from . import extraction, runner
    from .results import to_frame, write_atomic, write_results

    run_id = runner.new_run_id()
    out = Path(args.out) if args.out else DEFAULT_REPORTS / f"extract-{run_id}"
    if args.case:
        try:
            cases = catalog(args.case)
        except ValueError as exc:
            return _error(f"--case: {exc}")
        if not cases:
            return _error(f"--case: no case matches {args.case!r}; `python -m bench cases` lists them")
    else:
        cases = None
    from .rundir import claim_out

    try:
        lock = claim_out(out)  # new or empty, created, and this process's alone until it exits
    except ValueError as exc:
        return _error(str(exc))
    resolutions = tuple(args.resolution or (16, 32, 64, 128))
    from .heartbeat import Heartbeat

    lines = _ProgressLines(periodic=False)
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


def cmd_speed(args) -> int:
    from . import environment, speed
    from impls import METHODS, registry

    if args.method not in METHODS or METHODS[args.method].family != "root":
        roots = sorted(m for m, s in METHODS.items() if s.family == "root")
        return _error(f"--method: {args.method!r} is not a root finder; choose one of {roots}")
    try:
        METHODS[args.method].validate(dict(args.knobs or {}))
    except (ValueError, TypeError) as exc:
        return _error(f"--knobs: {exc}")
    if args.method == "raycast" and not args.mesh:
        return _error("--method raycast: an engine's query on meshes; time it with --mesh (the engines answer "
                      "raycast there whatever --method says)")
    args.side_given = args.side is not None
    if args.side is None:
        args.side = 1024
    environment.configure_threads(args.threads)
    allocator = environment.tune_allocator() if args.allocator == "tuned" else "default"
    if args.mesh:
        if args.volume:
            return _error("--mesh and --volume: choose one (mesh cameras are timed on root finders and engines)")
        return _speed_mesh(args, allocator)
    ids = _split(args.backend) if args.backend else [b.id for b in registry.available()[0]]
    bad = [(bid, b) for bid, b in ((bid, registry.resolve(bid)) for bid in ids) if isinstance(b, registry.Unavailable)]
    if bad:
        return _error("--backend: " + "; ".join(f"{bid}: {b.reason}" for bid, b in bad))
    if args.volume:
        from . import peers, speed

        rows, notes = peers.volume_rows(ids, speed.scenes(args.side if args.side_given else 256),
                                        n_samples=args.samples, repeats=args.repeats)
        for row in rows:
            row["threads"] = args.threads
            row["allocator"] = allocator
        print(f"volume rendering, {(args.side if args.side_given else 256)}² rays × {args.samples} samples, NeRF "
              f"density s = 50, no early termination, {args.threads} thread(s); time: median (min–max) of "
              f"{args.repeats}, compile and first call apart")
        print(peers.format_volume(rows))
        for line in notes:
            print(line)
        if args.out:
            from .results import write_json

            err = _write_out_file(args.out, lambda path: write_json(path, rows))
            if err:
                return _error(err)
        return 0
    notes: list[str] = []
    rows = speed.measure(ids, n_side=args.side, method=args.method, repeats=args.repeats, knobs=args.knobs or {},
                         threads=args.threads, peers=not args.no_peers, notes=notes)
    for row in rows:
        row["threads"] = args.threads
        row["allocator"] = allocator
    print(f"{args.side}² rays, {args.method}, {args.threads} thread(s) per library and root-finder driver, "
          f"allocator: {allocator}; × unit = time / numpy closed-form sphere hit of the same rays (same run, 1 thread)")
    if not args.no_peers:
        print("peers (bench/peers.py): peer:numba-st = numba per-ray sphere tracer (hit when φ < 1e-9, bounding-sphere "
              "clip); peer:scipy = hybrid_secant's march on numpy + scipy find_root (hybrid_chandrupatla)")
    print(speed.format_rows(rows))
    for line in notes:
        print(line)
    if args.out:
        from .results import write_json

        err = _write_out_file(args.out, lambda path: write_json(path, rows))
        if err:
            return _error(err)
    return 0


def _speed_mesh(args, allocator: str) -> int:
    """``speed --mesh`` (:mod:`bench.speed_mesh`): engines (raycast, float32) and root finders
    (``--method``, float64) on the three mesh cameras; default backends numpy, embree, open3d (an
    unavailable one is a line, not an error: its engine is not installed here)."""
    from impls import registry

    from . import speed_mesh

    ids = _split(args.backend) or list(speed_mesh.DEFAULT_BACKENDS)
    unknown = [bid for bid in ids if getattr(registry.resolve(bid), "unknown", False)]
    if unknown:
        return _error(f"--backend: {', '.join(unknown)} name no backend; `python -m bench backends` lists them")
    if args.knobs:
        return _error("--knobs: not with --mesh (each method runs at its default knobs there)")
    notes: list[str] = []
    lines = _ProgressLines(periodic=False)
    from .heartbeat import Heartbeat

    with Heartbeat(lines.line) as beat:
        rows = speed_mesh.measure(ids, n_side=args.side, method=args.method, repeats=args.repeats,
                                  peers=not args.no_peers, notes=notes, progress=beat.stage)
    for row in rows:
        row["threads"] = args.threads
        row["allocator"] = allocator
    print(f"mesh cameras, {args.side}² rays, {args.threads} thread(s); raycast (float32) where a backend offers it, "
          f"else {args.method} (float64, default knobs); × unit = time / numpy closed-form sphere hit of the same rays")
    print(speed_mesh.format_rows(rows))
    print("versions: " + speed_mesh.versions_line(rows))
    for line in notes:
        print(line)
    if args.out:
        from .results import write_json

        err = _write_out_file(args.out, lambda path: write_json(path, rows))
        if err:
            return _error(err)
    return 0


def cmd_sampling(args) -> int:
    """Samples per volume sampler to colour error targets (:mod:`bench.sampling`).  Every argument
    is checked before the costly reference integrals (one ``error:`` line, exit 2); progress lines
    come as each stage starts and at least every 30 s of it; ``--out`` is locked (a run directory
    has one writer) for the whole command."""
    from . import sampling
    from .environment import ROOT
    from .references import NotApplicable

    cases = [c.strip() for c in args.case.split(",") if c.strip()] if args.case is not None \
        else list(sampling.DEFAULT_CASES)
    try:
        targets = (tuple(float(t) for t in args.targets.split(",") if t.strip()) if args.targets is not None
                   else sampling.DEFAULT_TARGETS)
    except ValueError:
        return _error(f"--targets: {args.targets!r} must be comma-separated numbers, e.g. 1e-2,1e-3")
    try:
        sampling.check_arguments(cases, targets, args.sharpness)
    except ValueError as exc:
        return _error(str(exc))
    lock = None
    if args.out:
        from .rundir import RunLock, make_dir

        try:  # before minutes of work: a path that cannot be written, or a run directory being written
            lock = RunLock(make_dir(Path(args.out))).acquire()
        except ValueError as exc:
            return _error(str(exc))
        except OSError as exc:
            return _error(f"--out: cannot lock {args.out}: {exc.strerror or exc}; pass a directory you can write")
    lines = _ProgressLines(periodic=False)
    try:
        df = sampling.sampling_table(cases, targets, density=args.density, sharpness=args.sharpness,
                                     max_rays=args.max_rays, n_max=args.n_max, disk=ROOT / "reports" / ".refcache",
                                     progress=None if args.quiet else lines.line)
    except NotApplicable as exc:  # e.g. a density model with no continuous integral at these settings
        return _error(f"--case/--density/--sharpness: no rendering integral to sample towards: {exc}")
    print(sampling.markdown(df))
    if args.out:
        from .results import write_atomic

        out = Path(args.out)
        write_atomic(out / sampling.FILE, lambda tmp: df.to_csv(tmp, index=False))
        print(f"wrote {out / sampling.FILE}")
        if (out / "environment.json").exists():  # a run directory: its report gains the section
            from .report import build_from_dir

            build_from_dir(out)
            print(f"rebuilt {out / 'report.html'}")
        lock.release()
    return 0


def cmd_edges(args) -> int:
    """Wrong hits and misses of each engine against the grazing offset (:mod:`bench.edges`).  Every
    argument is checked before any ray is cast (one ``error:`` line, exit 2); a line as each stage
    starts and at least every 30 s of it; ``--out`` is locked for the whole command and its files
    (edges.csv, edges.png) written atomically; a run directory's report gains the section."""
    from . import edges
    from .heartbeat import Heartbeat

    try:
        def given(value, default):  # an option given empty stays empty, and check_arguments refuses it
            return list(default) if value is None else [v.strip() for v in value.split(",") if v.strip()]

        meshes = given(args.mesh, edges.DEFAULT_MESHES)
        families = given(args.family, edges.FAMILIES)
        try:
            offsets = [float(x) for x in given(args.offsets, edges.DEFAULT_OFFSETS)]
        except ValueError:
            raise ValueError(f"--offsets: {args.offsets!r} must be comma-separated numbers, e.g. 1e-2,1e-5,1e-9") from None
        edges.check_arguments(meshes, offsets, families, args.rays)
    except ValueError as exc:
        return _error(str(exc))
    ids = list(dict.fromkeys((_split(args.engines) or list(edges.DEFAULT_ENGINES)) + (_split(args.backend) or [])))
    from impls import registry

    unknown = [b for b in (_split(args.backend) or []) + (_split(args.engines) or []) if b not in (edges.TRIMESH, edges.TRIMESH_EMBREE)
               and getattr(registry.resolve(b), "unknown", False)]
    if unknown:
        return _error(f"--backend: {', '.join(unknown)} name no backend; `python -m bench backends` lists them")
    lock = None
    if args.out:
        from .rundir import RunLock, make_dir

        try:
            lock = RunLock(make_dir(Path(args.out))).acquire()
        except ValueError as exc:
            return _error(str(exc))
        except OSError as exc:
            return _error(f"--out: cannot lock {args.out}: {exc.strerror or exc}; pass a directory you can write")
    engines, notes = edges.engine_callables(ids, method=args.method)
    lines = _ProgressLines(periodic=False)
    for line in notes:
        lines.line(line)
    with Heartbeat(None if args.quiet else lines.line) as beat:
        df = edges.edges_table(engines, meshes=meshes, families=families, offsets=offsets, n_rays=args.rays,
                               seed=args.seed, stage=beat.stage)
    print("offset δ (× mesh size) at which each engine first returns a wrong answer (false hit, false miss, or a hit "
          "beyond its dtype's √ε depth tolerance), scanning δ downward:")
    print(edges.markdown(df))
    if args.out:
        from .results import write_atomic

        out = Path(args.out)
        write_atomic(out / edges.FILE, lambda tmp: df.to_csv(tmp, index=False))
        image = edges.plot(df, out / edges.PLOT)
        print(f"wrote {out / edges.FILE}" + (f", {image}" if image else ""))
        if (out / "environment.json").exists():  # a run directory: its report gains the section
            from .report import build_from_dir

            build_from_dir(out)
            print(f"rebuilt {out / 'report.html'}")
        lock.release()
    return 0


ALLOCATOR_HELP = ("tuned (default): glibc keeps freed memory instead of mmapping and faulting in fresh pages for "
                  "every large temporary (bench.environment.tune_allocator; recorded); default: leave malloc alone")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench", description="isobench: verify and time implicit-surface methods")
    sub = p.add_subparsers(dest="cmd", required=True)

    r = sub.add_parser("run", help="run a suite and write results and a report")
    r.add_argument("--suite", default="quick",
                   help="quick (CI, the showcase), full (every method on 3 cases, sweeps, float32, every workload "
                   "case) or workloads (the mesh, grid and neural cases only, default knobs)")
    r.add_argument("--backend", action="append", help="backend ids, comma-separated or repeated (default: all available)")
    r.add_argument("--method", action="append", help="methods to run (default: all in the suite)")
    r.add_argument("--case", help="glob(s) on case ids, comma-separated (default: the suite's); the matching cases run "
                   "each method with its whole knob sweep; '*' (the catalog sweep) still leaves out what the suite "
                   "excludes for cost, a glob that names cases runs them too")
    r.add_argument("--cases", action="append", help="your own cases: package.module:attribute (a Case, a list of them, or a function "
                   "returning either), comma-separated; they join the catalog tagged 'user' (reference/user_cases.py)")
    r.add_argument("--dtype", action="append", help="float64 and/or float32 (default: the suite's)")
    r.add_argument("--out", help="output directory (default: reports/<run-id>/)")
    r.add_argument("--min-time", type=_seconds, default=None, help="seconds of timed calls per configuration "
                   "(default: the suite's, 0.05 quick, 0.1 full)")
    r.add_argument("--max-time", type=_seconds, default=None, help="seconds of timed calls per configuration at most "
                   f"(default {DEFAULT_MAX_TIME_S:g}, or --min-time if larger; ≥ --min-time)")
    r.add_argument("--min-repeats", type=_int_at_least(1), default=None, help="timing samples per configuration at least "
                   "(default: the suite's, 3 quick, 5 full)")
    r.add_argument("--timeout", type=_seconds, default=120.0, help="hard limit per configuration in seconds; past it the "
                   "configuration is a failed 'timeout' row and the run goes on (default 120, 0: none)")
    r.add_argument("--threads", type=_int_at_least(1), default=1, help="threads per library (BLAS/OpenMP, torch, XLA), fixed and "
                   "recorded (default 1)")
    r.add_argument("--allocator", choices=("tuned", "default"), default="tuned", help=ALLOCATOR_HELP)
    r.add_argument("--accuracy-only", action="store_true", help="one call per configuration, no timing samples "
                   "(deterministic, for baselines)")
    r.add_argument("--resume", action="store_true", help="finish the interrupted run in --out DIR, with the plan "
                   "options it recorded (--suite, --case, --method, --dtype, --backend, --cases, --threads, "
                   "--allocator, --accuracy-only, --no-claims, --no-stability); every case is checked against the content hash "
                   "it was run with (see --rerun-case); the timing-sample options, --budget and --cluster are this session's")
    r.add_argument("--rerun-case", action="append", metavar="GLOB", help="with --resume: run these cases (globs on "
                   "ids, comma-separated) again from scratch when their content changed since the run started (their "
                   "old rows are dropped); without it a changed case refuses the resume, naming it")
    r.add_argument("--rounds", type=_int_at_least(1), default=1, help="time the whole plan this many times, round after round, "
                   "and pool the samples (robust run-to-run timing comparisons on a shared machine; default 1)")
    r.add_argument("--budget", type=_seconds, default=None, help="wall-clock guard against a hang, in seconds "
                   "(default none: the whole plan runs whatever the machine's speed; 0: none). A run that spends it "
                   "bounds the configuration in flight, records what is left as skipped 'over budget' rows, is marked "
                   "incomplete and exits 1; --resume finishes it")
    r.add_argument("--no-claims", action="store_true", help="do not run the claims ledger at the end")
    r.add_argument("--no-stability", action="store_true", help="do not run the suite's stability stage (every root "
                   "finder × dtype on one case per adversarial ray family, accuracy only, into stability/)")
    r.add_argument("--reference-timeout", type=_seconds, default=30.0, help="seconds for one costly reference answer (a "
                   "rendering integral for one case and density); past it that quantity is skipped with the reason, "
                   "and that density is not retried in this run (default 30, 0: none)")
    r.add_argument("--no-reference-cache", action="store_true", help="recompute costly reference answers (the "
                   "rendering integral) instead of reusing those kept in the cache directory")
    r.add_argument("--cache-dir", help="where compiled kernels (jax, numba) and costly reference answers are kept "
                   "between runs (default: $XDG_CACHE_HOME/isobench, else ~/.cache/isobench; recorded as cache_dir)")
    r.add_argument("--no-cache", action="store_true", help="a cold start: no persistent cache is read or written, "
                   "every kernel is compiled afresh")
    r.add_argument("--cluster", metavar="local:N", help="run the configurations as tasks on a dask LocalCluster of N "
                   "single-threaded worker processes (bench/cluster.py; N × --threads ≤ cores unless --accuracy-only); "
                   "results, resume and the report are those of a run in one process, each row records its worker")
    r.add_argument("--scheduler", metavar="ADDRESS", help="run the configurations on an existing dask cluster "
                   "(e.g. tcp://host:8786); its workers need this isobench and, for timing, --nthreads 1")
    r.add_argument("--no-progress", action="store_true", help="no live progress bar and no periodic progress lines "
                   "(stage lines and the summary still print; without it, progress is a live bar on a terminal and "
                   "plain lines when piped)")
    r.set_defaults(fn=cmd_run)
    r.set_defaults(run_option_defaults={dest: r.get_default(dest) for dest in RESUMED_OPTIONS})

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
    c.add_argument("--allow-missing", action="store_true", help="pass although rows of BASE are missing in NEW "
                   "(comparing a partial selection on purpose); by default missing rows fail the comparison")
    c.add_argument("--min-comparable", type=_share, default=1.0, metavar="SHARE",
                   help="fail unless at least this share of BASE's rows were compared (not 'not comparable': "
                   "a changed case version, a row over a time budget); default 1 (all); a comparison of no row "
                   "always fails")
    c.set_defaults(fn=cmd_compare)

    cl = sub.add_parser("claims", help="check the lecture's claims; writes claims.csv, plots and a report")
    cl.add_argument("--out", help="output directory (default: reports/claims-<run-id>/)")
    cl.add_argument("--full", action="store_true", help="the full (slower) checks instead of the quick ones")
    cl.add_argument("--only", nargs="+", metavar="ID", help="claim ids to check (default: all), e.g. --only 2 7")
    cl.set_defaults(fn=cmd_claims)

    bl = sub.add_parser("baseline", help="regenerate the accuracy baseline that CI compares against")
    bl.add_argument("--out", default=str(DEFAULT_REPORTS / "baseline"), help="default: reports/baseline")
    bl.add_argument("--suite", default="quick")
    bl.add_argument("--backend", action="append", help="backend ids (default: all available)")
    bl.set_defaults(fn=cmd_baseline)

    k = sub.add_parser("cases", help="list the case catalog")
    k.add_argument("--case", help="glob on ids")
    k.add_argument("--tag", action="append", help="only cases with these tags")
    k.add_argument("--cases", action="append", help="also list your own cases: package.module:attribute (see run --cases)")
    k.set_defaults(fn=cmd_cases)

    ex = sub.add_parser("extract", help="marching cubes (scikit-image) at several grid resolutions, scored by "
                        "Hausdorff and Chamfer distance to the exact surface, with time (bench/extraction.py)")
    ex.add_argument("--case", help="glob(s) on case ids, comma-separated (default: one case per distinct scene and "
                    "the mesh cameras)")
    ex.add_argument("--resolution", type=_int_at_least(4), action="append",
                    help="grid points per axis, repeatable (default 16, 32, 64, 128)")
    ex.add_argument("--repeats", type=_int_at_least(1), default=3, help="timed repeats per configuration (default 3)")
    ex.add_argument("--out", help="output directory (default: reports/extract-<run-id>/); never overwritten")
    ex.set_defaults(fn=cmd_extract)

    sp_ = sub.add_parser("spread", help="how a run was spread over processes (workers, machine keys, tasks per "
                         "worker, wall and task time) and its projected wall time on more workers (bench/spread.py)")
    sp_.add_argument("run_dir")
    sp_.add_argument("--workers", type=_int_at_least(1), nargs="+", help="worker counts to project (default 1 2 4 8 16 "
                     "32 64)")
    sp_.add_argument("--overhead-s", type=_seconds, help="per-task overhead o in seconds (default: the run's measured "
                     "value; a single-process run has none)")
    sp_.add_argument("--central-s", type=_seconds, help="central (scheduler and client) seconds per task c (default: the "
                     "run's measured value)")
    sp_.set_defaults(fn=cmd_spread)

    b = sub.add_parser("backends", help="list backends and what they can do")
    b.set_defaults(fn=cmd_backends)

    rp = sub.add_parser("report", help="rebuild report.md/html of a run directory")
    rp.add_argument("run_dir")
    rp.set_defaults(fn=cmd_report)

    sp = sub.add_parser("speed", help="root finders on 2^20 rays at a sphere and a torus ∪ box, in units of the "
                        "closed-form sphere intersection (the backends issue's speed targets)")
    sp.add_argument("--backend", action="append", help="backend ids (default: all available)")
    sp.add_argument("--method", default="hybrid_secant")
    sp.add_argument("--knobs", type=_json_dict, help='JSON knob dict, e.g. \'{"xtol": 1e-8}\' (default: the method\'s defaults)')
    sp.add_argument("--side", type=_int_at_least(1), default=None, help="rays per image side (default 1024: 2^20 rays; "
                    "256 with --volume: 2^16 rays)")
    sp.add_argument("--no-peers", action="store_true", help="leave out the peers' rows (bench/peers.py: a numba per-ray "
                    "sphere tracer, scipy's Chandrupatla refiner)")
    sp.add_argument("--volume", action="store_true", help="volume rendering instead: each backend's volume_nerf_uniform "
                    "against the plain compositing compiled by torch.compile and jax.jit (bench/peers.py)")
    sp.add_argument("--mesh", action="store_true", help="the three mesh cameras instead: engines (raycast, float32) and "
                    "--method (float64) side by side, default backends numpy,embree,open3d (bench/speed_mesh.py)")
    sp.add_argument("--samples", type=_int_at_least(1), default=256, help="samples per ray with --volume (default 256)")
    sp.add_argument("--repeats", type=_int_at_least(1), default=3)
    sp.add_argument("--threads", type=_int_at_least(1), default=1, help="threads per library and worker threads of the numpy/torch "
                    "root-finder drivers (default 1)")
    sp.add_argument("--allocator", choices=("tuned", "default"), default="tuned", help=ALLOCATOR_HELP)
    sp.add_argument("--out", help="write the rows as JSON")
    sp.set_defaults(fn=cmd_speed)

    ed = sub.add_parser("edges", help="per engine, wrong hits/misses and depth error against the grazing offset at "
                        "mesh edges, vertices and faces parallel to the ray (bench/edges.py)")
    ed.add_argument("--backend", action="append", help="backends to add to embree, open3d, trimesh, "
                    "trimesh+embreex and numpy (e.g. warp,mitsuba): raycast where offered, else --method")
    ed.add_argument("--engines", action="append", help="replace the default engines (embree,open3d,trimesh,"
                    "trimesh+embreex,numpy) by these")
    ed.add_argument("--method", default="hybrid_secant", help="root finder of the backends without raycast "
                    "(float64, default knobs; default hybrid_secant)")
    ed.add_argument("--mesh", default=None, help="stored meshes, comma-separated (default torus,fin,blob)")
    ed.add_argument("--family", default=None, help="ray families, comma-separated (default edge,vertex,parallel)")
    ed.add_argument("--offsets", default=None, help="grazing offsets × mesh size (default 1e-2,1e-3,…,1e-9)")
    ed.add_argument("--rays", type=_int_at_least(2), default=64, help="rays per mesh, family and offset (default 64)")
    ed.add_argument("--seed", type=int, default=0)
    ed.add_argument("--out", help="write edges.csv and edges.png there; a run directory's report then shows them")
    ed.add_argument("--quiet", action="store_true", help="no progress lines")
    ed.set_defaults(fn=cmd_edges)

    sm = sub.add_parser("sampling", help="samples per ray each volume sampler needs to reach colour error targets "
                        "against the rendering integral (bench/sampling.py)")
    sm.add_argument("--case", help="case ids, comma-separated (default: sphere.camera.64x64,torus.camera.32x32)")
    sm.add_argument("--targets", help="colour error targets, comma-separated (default 1e-2,1e-3,1e-4)")
    sm.add_argument("--density", default="nerf", choices=("nerf", "volsdf", "neus"), help="density model (default nerf)")
    sm.add_argument("--sharpness", type=float, default=50.0, help="density sharpness s, finite and > 0 (default 50)")
    sm.add_argument("--max-rays", type=_int_at_least(1), default=64, help="reference rays per case (default 64)")
    sm.add_argument("--n-max", type=_int_at_least(4), default=4096, help="largest N searched (default 4096)")
    sm.add_argument("--out", help="write sampling.csv there; a run directory's report then shows the table")
    sm.add_argument("--quiet", action="store_true", help="no progress lines")
    sm.set_defaults(fn=cmd_sampling)

    args = p.parse_args(argv)
    try:
        return args.fn(args)
    except BrokenPipeError:  # stdout closed early (`| head`): stop quietly, as a pipe's reader expects
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at exit's flush
        return 1


if __name__ == "__main__":
    sys.exit(main())
