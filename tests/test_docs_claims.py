"""docs/claims.md lists every claim of the ledger with where the lecture makes it, so that a
reader needs nothing outside the repository.  The page is generated from the ledger itself;
``ISOBENCH_WRITE_DOCS=1 python -m pytest tests/test_docs_claims.py`` rewrites it."""

from __future__ import annotations

import os
from pathlib import Path

DOC = Path(__file__).resolve().parents[1] / "docs" / "claims.md"

LECTURE = ("Binbin Huang, *Implicit Representation Is All You Need I Know — Introduction to Differentiable "
           "Implicit Surface*, lecture slides, ShanghaiTech University, 2021")

HEAD = f"""# The lecture's claims and how isobench checks them

isobench checks the claims of {LECTURE} (cited below as "the lecture"; slide titles and equation
numbers are the lecture's). Every claim is a module of `bench/claims/` (`c<NN>_<topic>.py`), run by
`python -m bench claims` and by every `python -m bench run` (the report's "Claims" section, with the
verdict, the counterexample where one was found, and a plot per claim).

A verdict is judged inside the claim's **scope** (the assumptions the lecture states or implies):
*holds* (every trial inside the scope holds), *holds under conditions* (the trials that fail share a
named class, which the report states), *fails* (a counterexample inside the scope, which the report
shows), *error* (the check could not run). Trials outside the scope are reported, never counted.

This page is generated from the ledger (`tests/test_docs_claims.py` checks it is current).
"""


def _cell(text: str) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def render() -> str:
    from bench.claims import LEDGER, _load

    _load(LEDGER)
    rows = [HEAD, "", "| id | the claim | where the lecture makes it | scope | how isobench checks it |",
            "|---|---|---|---|---|"]
    # in the ledger's numbering (1a, 1b, 2a, …, 12), whatever order the claim modules were imported in
    def number(c):
        digits = "".join(ch for ch in c.id if ch.isdigit())
        return int(digits), c.id[len(digits):]

    for c in sorted(LEDGER._claims.values(), key=number):
        rows.append(f"| {c.id} | {_cell(c.statement)} | {_cell(c.equation)} | {_cell(c.scope) or '—'} | "
                    f"{_cell(c.how_checked)} |")
    return "\n".join(rows) + "\n"


def test_docs_claims_lists_every_claim_of_the_ledger():
    text = render()
    if os.environ.get("ISOBENCH_WRITE_DOCS") == "1":
        DOC.write_text(text, encoding="utf-8")
    assert DOC.exists(), "docs/claims.md is missing: ISOBENCH_WRITE_DOCS=1 python -m pytest tests/test_docs_claims.py"
    assert DOC.read_text(encoding="utf-8") == text, (
        "docs/claims.md is out of date with bench/claims: ISOBENCH_WRITE_DOCS=1 python -m pytest tests/test_docs_claims.py")
