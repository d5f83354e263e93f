"""Resuming a run: the environment and rows an interrupted run left in its directory, which of
its configurations are done, and whether its cases are still the ones it ran
(:func:`check_case_versions`)."""

from __future__ import annotations

import fnmatch
import json
from pathlib import Path

from .plan import CONFIG_KEY, Config
from .results import OVER_BUDGET, read_results, remove_temporaries


def load_previous(out_dir: Path) -> tuple[dict, object]:
    """(environment, rows or None) of the partial run in ``out_dir``, the environment marked as
    one more session; temporary files that killed writers left are removed first.  A ValueError
    names what is missing or broken and the fix."""
    if not (out_dir / "environment.json").exists():
        raise ValueError(f"--resume: {out_dir} holds no run to resume (no environment.json); drop --resume")
    remove_temporaries(out_dir)
    try:
        env = json.loads((out_dir / "environment.json").read_text())
        env["run_id"]
    except (ValueError, KeyError) as exc:
        raise ValueError(f"--resume: {out_dir / 'environment.json'} is not a run's environment "
                         f"({type(exc).__name__}: {exc}); start a new run with another --out") from None
    try:
        previous = read_results(out_dir)
    except FileNotFoundError:
        previous = None
    env["resumed"] = str(int(env.get("resumed", "0")) + 1)
    if "elapsed_sessions_s" not in env:  # a run recorded before sessions were
        env["elapsed_sessions_s"] = json.dumps([float(env["elapsed_s"])] if env.get("elapsed_s") else [])
    return env, previous


def kept_rows(previous) -> tuple[list[dict], set[tuple]]:
    """The rows of a resumed run that stay and the configuration keys they cover; rows the
    budget left unmeasured (:data:`OVER_BUDGET`) are dropped, so those configurations run again."""
    if previous is None:
        return [], set()
    over = previous["reason"].fillna("").astype(str).str.startswith(OVER_BUDGET)
    rows = [r for r, o in zip(previous.to_dict("records"), over) if not o]
    return rows, _done_keys(previous[~over])


def outcome_counts(rows: list[dict]) -> dict[str, int]:
    """Configurations by outcome (``ok``, ``skipped``, ``failed``) among ``rows``."""
    counts = {"ok": 0, "skipped": 0, "failed": 0}
    kept: dict[tuple, list[dict]] = {}
    for r in rows:
        kept.setdefault(tuple(str(r[k]) for k in CONFIG_KEY), []).append(r)
    for g in kept.values():
        counts[outcome_of(g)] += 1
    return counts


def check_case_versions(previous, cfgs: list[Config], rerun_cases: list[str] | None = None):
    """The rows of a resumed run that may be kept: every planned case's recorded ``case_version``
    must be its version now (its content hash, :attr:`reference.cases.Case.version`), else the
    finished run would mix rows of two versions of one case (an unseeded user factory, an edited
    module).  A changed case matching a glob of ``rerun_cases`` has its old rows dropped (it runs
    again, whole); any other is a ValueError naming it, both versions and the fix.  Returns
    ``previous`` less the dropped rows."""
    if previous is None or not len(previous) or "case_version" not in previous.columns:
        return previous
    now = {c.case.id: str(c.case.version) for c in cfgs}
    recorded = previous.groupby("case_id")["case_version"].agg(lambda v: sorted(set(map(str, v))))
    changed = {cid: vs for cid, vs in recorded.items() if cid in now and vs != [now[cid]]}
    rerun = {cid for cid in changed if any(fnmatch.fnmatchcase(cid, g) for g in rerun_cases or ())}
    refused = sorted(set(changed) - rerun)
    if refused:
        shown = "; ".join(f"{cid} (recorded version {', '.join(changed[cid])}, now {now[cid]}: "
                          f"{int((previous['case_id'] == cid).sum())} rows)" for cid in refused[:5])
        more = f" and {len(refused) - 5} more" if len(refused) > 5 else ""
        raise ValueError(f"--resume: {len(refused)} case(s) changed since the run started: {shown}{more}; their rows "
                         f"would mix two versions of one case. Pass --rerun-case '{','.join(refused[:5])}' to drop "
                         "their rows and run them again, or start a new run with another --out")
    return previous[~previous["case_id"].isin(rerun)] if rerun else previous


def _done_keys(df) -> set[tuple]:
    if df is None or not len(df):
        return set()
    return set(map(tuple, df[CONFIG_KEY].astype(str).itertuples(index=False, name=None)))


def outcome_of(rows: list[dict]) -> str:
    """A configuration's outcome from its rows: ``ok`` if any quantity was measured, else
    ``failed`` if any failed, else ``skipped`` (as ``bench.report.tables.config_outcomes``)."""
    outs = {r.get("outcome") for r in rows}
    return "ok" if "ok" in outs else "failed" if "failed" in outs else "skipped"


def record_elapsed(env: dict, session_s: float) -> None:
    """Record this session's seconds: ``elapsed_sessions_s`` (a JSON list, one entry per session
    of the run: the first and every ``--resume``) and ``elapsed_s``, their sum."""
    sessions = json.loads(env.get("elapsed_sessions_s") or "[]")
    sessions[-1] = round(session_s, 1)
    env["elapsed_sessions_s"] = json.dumps(sessions)
    env["elapsed_s"] = f"{sum(sessions):.1f}"

