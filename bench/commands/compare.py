"""``python -m bench compare``."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ._common import error, make_console, share, write_out_file

ORDER = 1
HELP = ("compare two runs; exit 1 on regression")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("base")
    p.add_argument("new")
    p.add_argument("--factor", type=float, default=1.1, help="timing: slower by more than this factor … (default 1.1)")
    p.add_argument("--alpha", type=float, default=0.01, help="… and significant at this level (default 0.01)")
    p.add_argument("--rtol", type=float, default=0.1, help="accuracy: relative slack on the max error (default 0.1)")
    p.add_argument("--atol-eps", type=float, default=1000.0, help="accuracy: absolute slack in units of the row's "
                   "dtype eps (default 1000)")
    p.add_argument("--timing", action="store_true", help="also fail on significant timing regressions")
    p.add_argument("--out", help="write the comparison table as csv")
    p.add_argument("--allow-missing", action="store_true", help="pass although rows of BASE are missing in NEW "
                   "(comparing a partial selection on purpose); by default missing rows fail the comparison")
    p.add_argument("--min-comparable", type=share, default=1.0, metavar="SHARE",
                   help="fail unless at least this share of BASE's rows were compared (not 'not comparable': "
                   "a changed case version, a row over a time budget); default 1 (all); a comparison of no row "
                   "always fails")


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
    from ..run.results import OVER_BUDGET

    over = int(df["reason"].fillna("").astype(str).str.startswith(OVER_BUDGET).sum()) if "reason" in df else 0
    if env is not None and str(env.get("complete", "true")) != "true":
        return f"{name} is an incomplete run: {env.get('incomplete_reason', 'complete=false in environment.json')}"
    if over:
        return f"{name} has {over} rows not measured ({OVER_BUDGET})"
    return ""


def run(args) -> int:
    import pandas as pd

    from ..report import compare as cmp
    from ..run.results import read_results, write_text

    try:
        base, new = read_results(args.base), read_results(args.new)
    except FileNotFoundError as exc:
        return error(f"BASE/NEW: {exc}")
    except ValueError as exc:
        return error(f"BASE/NEW: {exc}; pass two run directories (or their results.parquet/.csv)")
    eb, en = _run_env(args.base), _run_env(args.new)
    from ..run.environment import machine_key

    # each row's machine: its own key (a cluster run's rows record their worker's), else its run's
    for df, env in ((base, eb), (new, en)):
        own = df["machine_key"].fillna("").astype(str) if "machine_key" in df else None
        if env is not None:
            df["machine_key"] = machine_key(env) if own is None else own.where(own != "", machine_key(env))
    try:
        res = cmp.compare(base, new, factor=args.factor, alpha=args.alpha, rtol=args.rtol, atol_eps=args.atol_eps,
                          same_machine=True)  # the rows' machine keys decide (same_row_machine)
    except ValueError as exc:
        return error(str(exc))
    console = make_console()
    counts = {col: res[col].value_counts().to_dict() for col in ("accuracy", "timing")}
    worse = res[(res["accuracy"] == "worse") | ((res["timing"] == "worse") & args.timing)]
    if args.out:
        err = write_out_file(args.out, lambda path: write_text(path, res.to_csv(index=False)))
        if err:
            return error(err)
    if len(worse):
        from rich.markup import escape

        cols = [c for c in ["case_id", "backend", "dtype", "method", "knob", "quantity", "accuracy", "error_base",
                            "error_new", "timing", "time_ratio", "p_value", "note"] if c in worse.columns]
        console.print(escape(worse[cols].to_string(index=False)))
    console.print(f"accuracy: {counts['accuracy']}")
    differ = int((res.get("note", pd.Series(dtype=str)).fillna("") == "timing measured on different machines").sum())
    console.print(f"timing:   {counts['timing']}" + (f" ({differ} rows measured on different machines: timing not "
                                                      "compared)" if differ else "")
                  + ("" if args.timing else " (shown, not gating: --timing fails on a timing regression)"))
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
        error(p, 1)
    if len(worse) or problems:
        return 1
    console.print("no regression")
    return 0

