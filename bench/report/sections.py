"""The report of a run as a :class:`bench.report.document.Document`, section by section, in
reading order:

1. *First screen* (:mod:`bench.report.summary`): failed configurations, regressions against a
   baseline when given, which to pick, the stability scoreboard, the claims' verdicts.
2. *Best accuracy per backend* — per case, method, quantity and backend: the knob setting with
   the smallest max error, its median time, IQR, time in units of the closed-form ray–sphere
   intersection of the same rays, compile time and evaluations per ray.
3. *Fastest configuration reaching an error target* (1e-4, 1e-8, 1e-12).
4. *Stability matrix* (:mod:`bench.studies.stability`): the scoreboard, then every root finder
   × backend × dtype against each adversarial ray family at default knobs, from the run's
   stability stage (``stability/``) when it has one, else from the run's own rows.
5. *Compile time, cold and warm* (per backend), then *Time versus error* and *Convergence* plots (:mod:`bench.report.plots`) with the fitted rates.
6. *Support matrix* (backend × method: configurations ran / skipped / failed) and the reasons.
7. *Claims ledger* when the run directory has ``claims.csv`` (plots inlined).
8. *Samples to a colour error target* when the directory has ``sampling.csv``.
9. *Engines at the edge* when the directory has ``edges.csv`` (:mod:`bench.studies.edges`).
10. *How the run was spread* (:mod:`bench.report.spread`).
11. *Environment*.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from . import summary
from .document import Bullets, Cell, Document, Figure, Figures, Grid, Group, Heading, Paragraph, Preformatted, Table
from .tables import (CLAIM_COLUMNS, claims_in_reading_order, compile_table, config_outcomes, fastest_to_target, not_run, rates_table,
                     spread_section, summary_table, support_matrix)

STABILITY_RULE = (
    "✓ survived: no false hit, no hitting ray reported MISS, every CONVERGED depth within "
    "min(√ε(dtype)·max(1, T) + 100ε(dtype)·R, S/4) (T the case's largest depth, R its hitting rays' largest origin "
    "norm, S its scene's diameter); ⚑ flagged: no wrong answer, but some rays declined with a failure status "
    "(MAX_ITER, NON_FINITE, LIPSCHITZ_VIOLATED, UNCERTIFIED…) — counts as survived; ✗ failed: a silent wrong "
    "answer or a failed configuration; — not run; ? not judged: the reference flags every ray of the cell's cases "
    "(e.g. exact tangents float64 cannot call a touch or a miss; rays it flags elsewhere are left out). Cells: "
    "mark · max depth error of the CONVERGED rays (— none converged) · worst field evaluations per ray; default "
    "knobs. float32 cells are judged against the float64 rays' exact depths. The Lipschitz methods certify their "
    "answers (docs/methods.md, \"What each root finder can miss\"); the constant-step marchers (march_*) step "
    "without a bound and certify by their samples' spheres: a crossing within step + xtol of the first, a MISS "
    "where every step is covered; a feature crossed twice within a step leaves them ⚑ where the spheres fall short.")


def first_screen(fs: dict) -> Group:
    """The first screen (:func:`bench.report.summary.first_screen`)."""
    out = []
    if fs["failures"]:
        out += [Heading("Failed configurations", warn=True), Bullets(tuple(fs["failures"]))]
    if fs["regressions"] is not None:
        out += [Heading(f"Regressions against the baseline: {len(fs['regressions'])}"), Table(fs["regressions"])]
    out += [Heading("Which to pick"), Paragraph(summary.PICK_NOTE), Table(fs["picks"])]
    if fs["scoreboard"]:
        out += [Heading("Stability scoreboard"), Bullets(tuple(fs["scoreboard"]))]
    if len(fs["claims"]):
        out += [Heading("Claims of the lecture (failures first)"),
                Paragraph("One line per claim, failures first; scope, evidence and plots in the claims ledger at "
                          "the end."), Table(fs["claims"])]
    return Group("first-screen", tuple(out))


def stability(cells: pd.DataFrame, note: str) -> list:
    from ..studies import stability as st

    out = [Heading("Stability matrix", anchor="stability")]
    if not len(cells):
        return out + [Paragraph("No root finder ran on an adversarial case (the quick suite's stability stage or "
                                "`python -m bench run --suite stability` runs them).")]
    m = st.stability_matrix(cells, detail=True)
    fams = [c for c in m.columns if c not in ("method", "backend", "dtype")]
    css = {"✓": "ok", "⚑": "flag", "✗": "bad", "—": "na"}
    rows = tuple(tuple(Cell(str(r[c])) for c in ("method", "backend", "dtype"))
                 + tuple(Cell(r[f][0], css=f"st {css.get(r[f][0][:1], 'na')}", title=r[f][1]) for f in fams)
                 for _, r in m.iterrows())
    out += [Bullets(tuple(st.scoreboard_lines(st.scoreboard(cells))), css="board"),
            Paragraph(f"{STABILITY_RULE} Hover a cell (HTML) for its statuses, false hits and misses, and cases. "
                      f"Source: {note}."),
            Grid(("method", "backend", "dtype", *fams), rows, css="t stab")]
    bad = cells[cells["verdict"].isin(["failed", "flagged"])]
    if len(bad):
        out += [Paragraph("Failed and flagged cells:", style="plain"),
                Bullets(tuple(f"{r['method']} · {r['backend']} · {r['dtype']} · {r['family']}: {st.cell_detail(r)}"
                              for _, r in bad.iterrows()))]
    return out


def claims_ledger(claims: pd.DataFrame, run_dir: Path) -> list:
    """A one-line-per-claim summary (failures first, so every verdict and the scope it was judged
    in come before the evidence), then the evidence with each claim's plot below its row."""
    def is_warn(verdict: str) -> bool:
        return verdict.lower() not in ("holds", "true", "confirmed")

    def cells(r, cols) -> tuple[Cell, ...]:
        verdict = str(r.get("verdict", ""))
        return tuple(Cell(str(r[c]), css="warn" if c == "verdict" and is_warn(verdict) else None,
                          folded=c == "key_numbers" and len(str(r[c])) > 200) for c in cols)

    short = [c for c in ("id", "statement", "scope", "verdict", "conditions", "counterexample") if c in claims.columns]
    names = {"conditions": "holds on (named class)", "counterexample": "counterexample (inside the scope)"}
    cols = [c for c in CLAIM_COLUMNS if c in claims.columns and c != "plot"]
    cols += [c for c in claims.columns if c not in CLAIM_COLUMNS]
    figures = []
    for _, r in claims.iterrows():
        plot = str(r.get("plot", "") or "")
        p = Path(run_dir) / plot
        ok = plot and p.is_file() and p.suffix.lower() == ".png"
        figures.append(Figure(f"claim {r.get('id', '')}", p.read_bytes() if ok else None, plot) if plot else None)
    return [Grid(tuple(names.get(c, c) for c in short),
                 tuple(cells(r, short) for _, r in claims_in_reading_order(claims).iterrows())),
            Heading("Evidence, claim by claim", level=3),
            Grid(tuple(cols), tuple(cells(r, cols) for _, r in claims.iterrows()), tuple(figures))]


def _bench_sections(df: pd.DataFrame, figs: list, series_all: list, stab: list) -> list:
    """The sections of a run's measured rows (none for a claims-only directory)."""
    return [
        Heading("Best accuracy per backend"),
        Paragraph("Per case, method and checked quantity: the knob setting with the smallest max error over all "
                  "rays (color_vs_integral: over the rays the rendering integral is computed on, a fixed sample of "
                  "the case's; n_checked in results.csv). Time is the median over repeated synchronised calls (compile and first call excluded, "
                  "reported apart); IQR is its spread. '× closed form' divides by the time of the exact ray–sphere "
                  "formula on the same number of rays, measured right before and after the configuration's samples — "
                  "a unit that sees the same load as they do."), Table(summary_table(df)),
        Heading("Fastest configuration reaching an error target"),
        Paragraph("The cheapest knob setting whose max error is at or below the target: median time per call, its "
                  "multiple of the closed-form time, and the knob setting."), Table(fastest_to_target(df)),
        *stab,
        Heading("Compile time, cold and warm"),
        Paragraph("Per backend: the configurations whose kernel was compiled in this run (cold) and those that "
                  "reused one (warm: from the persistent cache, or compiled earlier in the run for the same "
                  "structure, its knobs traced)."), Table(compile_table(df)),
        Heading("Time versus error"),
        Paragraph("One plot per method family, case, quantity and dtype; one point per knob setting (faint "
                  "markers), a line through each backend's (and method's) Pareto-optimal settings; colour = method, "
                  "marker = backend; lower-left is better. ✕ at the top edge: an infinite error (a false hit or "
                  "miss, or a budget that ran out). Grey dashed steps: the Pareto front over every curve."),
        Figures(tuple(Figure(t, p, rel) for k, t, p, rel in figs if k == "time")),
        Heading("Convergence"),
        Paragraph("Error against an integer knob (step budget, iterations, samples) with the other knobs fixed, "
                  "log-log; the legend gives the fitted rate p of error ∝ knob^(−p) (least squares over the finite, "
                  "non-zero errors before the error floor; an algebraic rate — a geometric convergence shows as a "
                  "large p)."),
        Figures(tuple(Figure(t, p, rel) for k, t, p, rel in figs if k == "conv")), Table(rates_table(series_all)),
        Heading("Support matrix (configurations)"),
        Paragraph("Configurations (case × dtype × knob) per backend and method."), Table(support_matrix(df)),
    ]


def header(df: pd.DataFrame, env: dict) -> Paragraph:
    configs = config_outcomes(df)
    n_ok, n_skip, n_fail = ((configs["outcome"] == o).sum() for o in ("ok", "skipped", "failed"))
    status = (f"{n_ok} configurations ran, {n_skip} skipped, {n_fail} failed"
              + ("" if env.get("complete", "true") == "true" else " — **the run is incomplete** (finish it with --resume)"))
    return Paragraph(f"Run `{env.get('run_id', '?')}`, suite `{env.get('suite', '?')}`, commit `{env.get('commit', '?')}`, "
                     f"{env.get('cpu', '?')} ({env.get('cpu_count', '?')} logical CPUs, {env.get('threads', '?')} "
                     f"thread(s) per library). {status}.", style="plain")


def document(df: pd.DataFrame, env: dict, out_dir: Path, *, figs: list, series_all: list, stab_cells, stab_note: str,
             claims, fs: dict) -> Document:
    """The report of a run: its rows ``df``, environment ``env``, plots ``figs`` and the parts
    read from ``out_dir`` (stability cells, claims, sampling table)."""
    from ..studies.edges import section as edges_section
    from ..studies.sampling import section_md as sampling_md

    doc = Document(f"isobench report — run {env.get('run_id', '?')}", [header(df, env), first_screen(fs)])
    stab = stability(stab_cells, stab_note)
    doc.blocks += _bench_sections(df, figs, series_all, stab) if len(df) else []  # a claims-only directory
    skipped = not_run(df)
    if len(skipped):
        doc.blocks += [Heading("Skipped or failed, with reasons"), Table(skipped)]
    claims_note = env.get("claims", "")
    if claims is not None or (claims_note and claims_note != "ran"):
        doc.blocks.append(Heading("Claims ledger"))
        if claims_note and claims_note != "ran":
            doc.blocks.append(Paragraph(claims_note, style="warn"))
        if claims is not None:
            doc.blocks += claims_ledger(claims, out_dir)
    sampling = sampling_md(out_dir)
    if sampling:  # the study's own Markdown: a heading, a note and its table
        doc.blocks += [Heading(sampling[0].lstrip("# ")), Paragraph(sampling[2]), Preformatted(sampling[4])]
    edges = edges_section(out_dir)
    if edges:
        note, table, png = edges
        doc.blocks += [Heading("Engines at the edge"), Paragraph(note), Table(table),
                       Figures((Figure("engines at the edge", png.read_bytes() if png.is_file() else None, png.name),))]
    spread_lines, spread_workers = spread_section(df, env)
    if spread_lines:
        doc.blocks += [Heading("How the run was spread"), Bullets(tuple(spread_lines)),
                       Table(spread_workers, escape_pipes=True)]
    doc.blocks += [Heading("Environment"), Table(pd.DataFrame(sorted(env.items()), columns=["key", "value"]))]
    return doc
