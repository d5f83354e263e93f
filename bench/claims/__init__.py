"""The claims ledger: each claim of the lecture checked numerically, with a verdict and evidence.

Contract used by ``bench/cli.py`` (``python -m bench claims``) and by ``bench run`` (a section of
the main report): ``run_claims(out_dir, quick=True) -> pandas.DataFrame`` writes ``claims.csv``
(one row per claim) and one ``claim_<id>.png`` per claim into ``out_dir``.
"""

from __future__ import annotations

from pathlib import Path


def run_claims(out_dir: Path, *, quick: bool = True, only: list[str] | None = None):
    raise NotImplementedError("the claims ledger is not built yet (issue 6)")
