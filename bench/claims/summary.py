"""Text renderings of a claims table: a Markdown section for the report and a terminal summary."""

from __future__ import annotations

import json


def _cell(s: str, limit: int, markdown: bool = True) -> str:
    s = " ".join(str(s).split())
    if markdown:
        s = s.replace("|", "\\|")
    return s if len(s) <= limit else s[: limit - 1] + "…"


def markdown_section(df, *, plot_prefix: str = "", title: str = "Claims of the lecture") -> str:
    """A Markdown section: one table row per claim (id, statement, where, verdict, conditions /
    counterexample, plot link), then per claim its key numbers.  ``plot_prefix`` is prepended to the
    PNG names (the report's relative path to the claims folder)."""
    lines = [f"## {title}", "",
             "Verdicts are computed by one rule from the trials of each check (bench/claims/ledger.py): "
             "all trials hold → holds; none → fails; some → holds under conditions (listed).", "",
             "| id | statement | where | verdict | holds for / counterexample | plot |",
             "|---|---|---|---|---|---|"]
    for r in df.itertuples(index=False):
        detail = r.counterexample if r.verdict == "fails" else (
            f"holds for: {r.conditions}. Fails: {r.counterexample}" if r.verdict == "holds under conditions"
            else r.message if r.verdict == "error" else "")
        lines.append(f"| {r.id} | {_cell(r.statement, 160)} | {_cell(r.equation, 60)} | **{r.verdict}** | "
                     f"{_cell(detail, 400)} | [png]({plot_prefix}{r.plot}) |")
    lines.append("")
    for r in df.itertuples(index=False):
        lines.append(f"### Claim {r.id}: {r.verdict}")
        lines.append("")
        lines.append(f"*How checked:* {r.how_checked}")
        lines.append("")
        try:
            nums = json.loads(r.key_numbers) if isinstance(r.key_numbers, str) else {}
        except json.JSONDecodeError:
            nums = {}
        for k, v in nums.items():
            lines.append(f"- {k}: {v}")
        lines.append("")
        lines.append(f"![claim {r.id}]({plot_prefix}{r.plot})")
        lines.append("")
    return "\n".join(lines)


def terminal_summary(df) -> str:
    """One line per claim: id, verdict, seconds, and the counterexample or error (short)."""
    out = []
    for r in df.itertuples(index=False):
        extra = r.message if r.verdict == "error" else r.counterexample
        out.append(f"{r.id:>4}  {r.verdict:<24} {r.seconds:7.2f}s  {_cell(extra, 110, markdown=False)}")
    return "\n".join(out)
