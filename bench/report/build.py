"""Reports: ``report.md`` (plots as PNG files in ``plots/``) and a self-contained ``report.html``
(the same plots inlined as base64 PNG; no network, no scripts), both rendered from one model of
the run (:mod:`bench.report.sections`, :mod:`bench.report.document`)."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd

from . import document, plots, sections, summary
from .tables import STABILITY_DIR, read_claims, stability_section

__all__ = ["STABILITY_DIR", "build", "build_from_dir"]


def build(df: pd.DataFrame, env: dict, out_dir: Path, *, scoreboard: list[str] | None = None,
          regressions: pd.DataFrame | None = None):
    """Write ``report.md``, ``report.html`` and ``plots/*.png`` for results ``df`` into ``out_dir``;
    returns the first screen (:func:`bench.report.summary.first_screen`), which ``bench run``'s
    closing lines print (so the stability cells and claims are not read and judged twice).

    The first screen (:mod:`bench.report.summary`) comes first: failures, ``regressions`` against a
    baseline when given, "which to pick", the stability ``scoreboard`` lines (default: from the
    run's stability cells) and the claims' verdicts; then plots; the detail tables last."""
    out_dir = Path(out_dir)
    df = df.copy()
    for col, default in (("quantity", "depth"), ("family", "")):
        df[col] = df[col].fillna("").astype(str) if col in df else default
    jobs, series_all = plots.figure_jobs(df, out_dir)
    collect = plots.start_rendering(jobs)  # the figures draw in worker processes while the tables are built
    stab_cells, stab_note = stability_section(df, out_dir)
    claims = read_claims(out_dir)
    if scoreboard is None and len(stab_cells):
        from ..studies import stability

        scoreboard = stability.scoreboard_lines(stability.scoreboard(stab_cells))
    fs = summary.first_screen(df, env, claims=claims, scoreboard=scoreboard, regressions=regressions)
    rels = [str(path.relative_to(out_dir)) for _, _, _, path in jobs]
    figs = [(kind, title, None, rel) for (kind, title, _, _), rel in zip(jobs, rels)]  # PNGs filled in below
    doc = sections.document(df, env, out_dir, figs=figs, series_all=series_all, stab_cells=stab_cells,
                            stab_note=stab_note, claims=claims, fs=fs)
    document.fill_figures(doc, dict(zip(rels, collect())))
    document.write(doc, out_dir)
    return fs


def build_from_dir(run_dir: Path) -> None:
    """Rebuild the report of a run directory (a claims-only directory has no results)."""
    from ..run.results import COLUMNS, read_results

    run_dir = Path(run_dir)
    env = json.loads((run_dir / "environment.json").read_text())
    try:
        df = read_results(run_dir)
    except FileNotFoundError:  # a claims-only directory
        df = pd.DataFrame(columns=COLUMNS + ["knobs_json"])
    build(df, env, run_dir)
