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
             "Verdicts are computed by one rule from the trials of each check, judged inside each claim's "
             "scope (bench/claims/ledger.py): every trial in the scope holds → holds; some fail but a named "
             "class holds throughout → holds under conditions (the class); otherwise → fails. A bound that "
             "holds only where it is vacuous does not hold. Failures first.", "",
             "| id | statement | scope | verdict | holds on / counterexample | plot |",
             "|---|---|---|---|---|---|"]
    order = {"fails": 0, "error": 1, "holds under conditions": 2, "holds": 3}
    df = df.assign(_rank=df["verdict"].map(order).fillna(1)).sort_values("_rank", kind="stable")
    for r in df.itertuples(index=False):
        detail = r.counterexample if r.verdict == "fails" else (
            f"holds for: {r.conditions}. Fails outside it: {r.counterexample}" if r.verdict == "holds under conditions"
            else r.message if r.verdict == "error" else "")
        lines.append(f"| {r.id} | {_cell(r.statement, 160)} | {_cell(getattr(r, 'scope', ''), 200)} | **{r.verdict}** | "
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
