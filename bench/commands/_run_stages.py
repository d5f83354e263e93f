"""The stages of ``bench run`` after its configurations: the stability stage, the claims ledger,
the closing summary; and the cluster executor it may start before them."""

from __future__ import annotations

from pathlib import Path

from ._common import ProgressLines, split

def run_stability_into(out: Path, suite, backends: dict, args, console, executor=None) -> str:
    """The suite's stability stage (:func:`bench.studies.stability.run_stage`) into ``out/stability``;
    never raises.  Returns "" or a note saying why it did not complete."""
    import time

    from ..report.tables import STABILITY_DIR
    from ..studies.stability import run_stage

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


def start_executor(args, lines):
    """The :class:`bench.run.cluster.ClusterExecutor` of ``--cluster``/``--scheduler`` (started), None
    without them, or an error message."""
    if not (args.cluster or args.scheduler):
        return None, ""
    if args.cluster and args.scheduler:
        return None, "--cluster and --scheduler: give one (local:N starts a cluster, --scheduler uses an existing one)"
    try:
        from ..run.cluster import ClusterExecutor, parse_local
    except ImportError as exc:
        return None, (f"--cluster/--scheduler need dask.distributed ({exc}); install it with "
                      "pip install -c constraints.txt -e '.[cluster]'")
    try:
        executor = ClusterExecutor(local=parse_local(args.cluster) if args.cluster else None, scheduler=args.scheduler,
                                   threads=args.threads, allocator=args.allocator,
                                   case_specs=tuple(split(args.cases) or ()), accuracy_only=args.accuracy_only,
                                   backend_specs=getattr(args, "specs", None))
        executor.start()
    except ValueError as exc:
        return None, str(exc)
    rec = executor.env_record()
    lines.line(f"cluster: {rec['cluster']} ({executor._capacity(fresh=True)} worker threads, started in "
               f"{rec['cluster.start_s']} s; {float(rec.get('cluster.central_s', 'nan')) * 1e3:.1f} ms central cost "
               "per task)")
    return executor, ""


def _first_screen_lines(df, env: dict, out: Path, fs=None) -> list[str]:
    """The report's answers in a few lines: which to pick at 1e-8, the stability scoreboard, the
    claims' verdict counts (:func:`bench.report.summary.first_screen`; ``fs``: the one the report
    was built with, else made here); nothing if they cannot be made."""
    from ..report import summary, tables
    from ..studies import stability

    try:
        if fs is None:
            cells, _ = tables.stability_section(df, out)
            board = stability.scoreboard_lines(stability.scoreboard(cells)) if len(cells) else []
            fs = summary.first_screen(df, env, claims=tables.read_claims(out), scoreboard=board)
        text = summary.terminal_text(fs).splitlines()[1:]  # the first line repeats the counts above
        return [t[:160] for t in text]
    except Exception as exc:  # the summary must never cost the run its exit code
        return [f"(summary unavailable: {type(exc).__name__}: {exc})"]


def closing_summary(df, env: dict, out: Path, lines: ProgressLines, fs=None) -> tuple[int, list[str]]:
    """The closing lines (counts, failures, incompleteness, report path; ``fs``: the report's first
    screen, :func:`bench.report.build.build`'s) and the exit code:
    0, or 1 when the run is incomplete (its --budget ran out), no configuration ran, or a stage
    beside the configurations failed (:func:`stage_errors`)."""
    from ..report.tables import config_outcomes

    configs = config_outcomes(df)
    n = {o: int((configs["outcome"] == o).sum()) for o in ("ok", "skipped", "failed")}
    from ..run.results import OVER_BUDGET

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
    said += _first_screen_lines(df, env, out, fs)
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
    errors += stage_errors(env, out)
    return (1 if errors else 0), errors


def stage_errors(env: dict, out: Path) -> list[str]:
    """What the run was asked for and could not do beside its configurations: a stability stage or
    claims ledger that failed (its note in environment.json, anything but "ran"), and claims whose
    check could not run (verdict ``error``, which ``bench claims`` exits 1 on too; "fails" is a
    verdict).  Each makes ``bench run`` exit 1 after writing the report, so that a CI job sees it;
    before, the run exited 0 with the section missing from its report."""
    from ..report.tables import read_claims

    errors = [f"{stage}: {env[stage]}" for stage in ("stability", "claims")
              if env.get(stage) not in (None, "", "ran")]
    if env.get("claims") == "ran":
        try:
            claims = read_claims(out)
            bad = ([str(i) for i, v in zip(claims["id"], claims["verdict"]) if v == "error"]
                   if claims is not None and len(claims) else [])
        except Exception as exc:  # noqa: BLE001 - an unreadable ledger is the error itself
            bad, errors = [], errors + [f"claims: the ledger {out / 'claims.csv'} cannot be read: {exc}"]
        if bad:
            errors.append(f"claims whose check could not run (verdict error): {', '.join(bad)}; see the report's "
                          "claims section (python -m bench claims --only ID reruns one)")
    return errors

