"""The report: tables computed right, plots present, the claims ledger inlined, failures visible."""

from __future__ import annotations

import base64
import json

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402
import pytest  # noqa: E402

import bench.claims  # noqa: E402
from bench import commands  # noqa: E402
from bench.commands._common import run_claims_into  # noqa: E402
from bench.report import build as report  # noqa: E402
from bench.report import plots, tables  # noqa: E402
from bench.run.results import to_frame  # noqa: E402


def frame():
    rows = []
    for bid, scale in (("numpy", 1.0), ("jax:cpu", 2.0)):
        for steps, err in ((4, 1e-3), (16, 1e-9), (64, 1e-13)):
            rows.append({"case_id": "c", "case_version": "v", "backend": bid, "dtype": "float64", "method": "m",
                         "family": "root", "knob": f"max_steps={steps}", "knobs_json": json.dumps({"max_steps": steps}),
                         "quantity": "depth", "unit": "scene units", "outcome": "ok", "reason": "",
                         "error_max": err, "error_iterate_median": err, "time_median_s": scale * steps * 1e-3,
                         "time_iqr_s": 0.0, "time_ratio_cf": scale * steps, "compile_s": 0.0, "evals_per_ray": steps})
    rows.append({"case_id": "c", "case_version": "v", "backend": "torch:cpu", "dtype": "float64", "method": "m",
                 "family": "root", "knob": "max_steps=4", "knobs_json": "{}", "quantity": "depth", "outcome": "skipped",
                 "reason": "backend unavailable: torch is not installed"})
    rows.append({"case_id": "c", "case_version": "v", "backend": "numpy", "dtype": "float64", "method": "m2",
                 "family": "root", "knob": "x=1", "knobs_json": "{}", "quantity": "depth", "outcome": "failed",
                 "reason": "RuntimeError: boom"})
    return to_frame(rows)


def test_fastest_to_target_and_support_matrix():
    t = tables.fastest_to_target(frame()).set_index("backend")
    assert t.loc["numpy", "≤ 1e-04"].startswith("16 ms") and "max_steps=16" in t.loc["numpy", "≤ 1e-04"]
    assert t.loc["jax:cpu", "≤ 1e-12"].startswith("128 ms") and "max_steps=64" in t.loc["jax:cpu", "≤ 1e-12"]
    t = tables.fastest_to_target(frame().assign(knob="")).set_index("backend")  # a method without knobs
    assert t.loc["numpy", "≤ 1e-04"] == "16 ms (×16)" and "@" not in t.loc["jax:cpu", "≤ 1e-12"]
    sup = tables.support_matrix(frame()).set_index("backend")
    assert sup.loc["numpy", "m"] == "ran 3" and sup.loc["numpy", "m2"] == "FAILED 1"
    assert sup.loc["torch:cpu", "m"] == "skipped 1" and sup.loc["torch:cpu", "m2"] == "not planned"
    reasons = tables.not_run(frame())
    assert {"backend unavailable: torch is not installed", "RuntimeError: boom"} == set(reasons["reason"])


def test_report_inlines_the_claims_ledger(tmp_path):
    fig, ax = plt.subplots()
    ax.plot([1, 2], [3, 4])
    fig.savefig(tmp_path / "claim_c1.png")
    plt.close(fig)
    pd.DataFrame([{"id": "c1", "statement": "Δφ = κ1 + κ2", "equation": "(5)", "how_checked": "sphere",
                   "verdict": "holds", "key_numbers": "max err 1e-12", "plot": "claim_c1.png"},
                  {"id": "c2", "statement": "a false one", "equation": "(9)", "how_checked": "grid",
                   "verdict": "fails", "key_numbers": "counterexample x=1", "plot": "missing.png"}]
                 ).to_csv(tmp_path / "claims.csv", index=False)
    report.build(frame(), {"run_id": "r", "claims": "ran"}, tmp_path)
    html = (tmp_path / "report.html").read_text()
    assert "Claims ledger" in html and "Δφ = κ1 + κ2" in html and "counterexample x=1" in html
    assert base64.b64encode((tmp_path / "claim_c1.png").read_bytes()).decode() in html
    assert "plot missing.png not found" in html
    md = (tmp_path / "report.md").read_text()
    assert "![claim c1](claim_c1.png)" in md and "missing.png)" not in md
    for p in (tmp_path / "plots").glob("*.png"):
        assert p.stat().st_size > 1000
    series = plots.convergence_series(frame())
    assert {(s["backend"], s["knob"], tuple(s["x"])) for s in series} == {
        ("numpy", "max_steps", (4.0, 16.0, 64.0)), ("jax:cpu", "max_steps", (4.0, 16.0, 64.0))}


def test_claims_failure_is_a_visible_note_not_a_crash(tmp_path, monkeypatch):
    def broken(out_dir, *, quick=True, only=None, reference_dir=None):
        raise RuntimeError("ledger exploded")

    monkeypatch.setattr(bench.claims, "run_claims", broken)

    class Quiet:
        def print(self, *a, **k):
            pass

    note = run_claims_into(tmp_path, quick=True, console=Quiet())
    assert note == "claims failed: RuntimeError: ledger exploded"
    report.build(frame(), {"run_id": "r", "claims": note}, tmp_path)
    assert "claims failed: RuntimeError: ledger exploded" in (tmp_path / "report.html").read_text()
    assert "claims failed" in (tmp_path / "report.md").read_text()


def test_claims_subcommand_calls_run_claims(tmp_path, monkeypatch, capsys):
    seen = {}

    def fake(out_dir, *, quick=True, only=None, reference_dir=None):
        seen.update(quick=quick, only=only)
        df = pd.DataFrame([{"id": "7", "statement": "s", "equation": "(1)", "how_checked": "h", "verdict": "holds",
                            "key_numbers": "{}", "plot": "", "seconds": 0.5, "counterexample": "", "message": ""}],
                          columns=bench.claims.COLUMNS)
        out_dir.mkdir(parents=True, exist_ok=True)
        df.to_csv(out_dir / "claims.csv", index=False)
        return df

    monkeypatch.setattr(bench.claims, "run_claims", fake)
    assert commands.main(["claims", "--out", str(tmp_path / "cl"), "--full", "--only", "7"]) == 0
    assert seen == {"quick": False, "only": ["7"]}
    assert "Claims ledger" in (tmp_path / "cl" / "report.html").read_text()
    assert "### Claim 7: holds" in (tmp_path / "cl" / "claims.md").read_text()  # the ledger as Markdown
    assert any(line.split()[:2] == ["7", "holds"] for line in capsys.readouterr().out.splitlines())
    # an unknown id is a usage error naming the argument, before anything runs
    seen.clear()
    assert commands.main(["claims", "--out", str(tmp_path / "cl2"), "--only", "7", "no-such-claim"]) == 2
    assert "--only: unknown claim id(s) no-such-claim" in capsys.readouterr().err
    assert seen == {} and not (tmp_path / "cl2").exists()


def test_knob_labels_show_only_what_differs_from_the_defaults():
    from bench.report.tables import knob_label
    from bench.run.results import knob_string
    from impls.methods import METHODS

    defaults = {k.name: k.default for k in METHODS["hybrid_secant"].knobs}
    assert knob_label("hybrid_secant", knob_string(defaults)) == "defaults"
    assert knob_label("hybrid_secant", knob_string(dict(defaults, xtol=1e-8))) == "xtol=1e-08"
    assert knob_label("hybrid_secant", knob_string(dict(defaults, xtol=1e-8, ladder=0))) == "ladder=0,xtol=1e-08"
    assert knob_label("normal", "") == ""
    assert knob_label("not_in_the_catalog", "max_steps=16,tol=1e-06") == "max_steps=16,tol=1e-06"


def _stability_rows():
    from impls.methods import METHODS

    from bench.run.results import knob_string

    knob = knob_string({k.name: k.default for k in METHODS["sphere_trace"].knobs})
    base = {"schema_version": 2, "case_version": "v", "method": "sphere_trace", "family": "root", "knob": knob, "knobs_json": "{}",
            "quantity": "depth", "unit": "scene units", "outcome": "ok", "reason": "", "evals_max": 41,
            "iterations_max": 40, "n_miss_declined": 0, "n_converged_nonfinite": 0}
    rows = []
    for bid in ("numpy", "jax"):
        rows.append({**base, "case_id": "sphere.grazing.1e-6", "backend": bid, "dtype": "float64", "error_max": 2e-16,
                     "error_max_finite": 2e-16, "n_false_hit": 0, "n_false_miss": 0,
                     "status_counts": json.dumps({"CONVERGED": 128, "MISS": 128})})
        rows.append({**base, "case_id": "shell.understated.L10", "backend": bid, "dtype": "float64",
                     "error_max": float("inf"), "error_max_finite": 0.0, "n_false_hit": 0, "n_false_miss": 256,
                     "status_counts": json.dumps({"MISS": 256}), "evals_max": 2})
    # a sweep point (not default knobs) that would fail the cell: the matrix judges default knobs only
    rows.append({**rows[0], "knob": "max_steps=4,tol=1e-10", "n_false_miss": 7, "error_max": float("inf")})
    return to_frame(rows)


def test_report_stability_section_scoreboard_then_matrix_after_the_first_tables(tmp_path):
    from bench.run.results import write_results

    write_results(_stability_rows(), tmp_path / report.STABILITY_DIR)
    report.build(frame(), {"run_id": "r"}, tmp_path)
    html = (tmp_path / "report.html").read_text()
    i_fast, i_stab, i_time = (html.index(s) for s in ("Fastest configuration", "Stability matrix", "Time versus error"))
    assert i_fast < i_stab < i_time
    sec = html[i_stab:i_time]
    board = "numpy (float64): 1/2 families survived (1/2 cells, 0 of them flagged); failed: understated"
    assert board in sec and "jax (float64): 1/2" in sec
    assert sec.index(board) < sec.index("<table")
    assert "✓ 2e-16 · 41" in sec and "✗ — · 2" in sec  # no ray converged on the understated case
    assert "256 hitting ray(s) reported MISS" in sec and "title=" in sec
    assert "stability stage" in sec
    md = (tmp_path / "report.md").read_text()
    m_fast, m_stab, m_time = (md.index(s) for s in ("## Fastest configuration", "## Stability matrix",
                                                     "## Time versus error"))
    assert m_fast < m_stab < m_time
    assert f"- {board}" in md and "| understated" in md.replace("|  ", "| ")


def test_report_stability_section_without_a_stage_uses_the_runs_rows_or_says_none(tmp_path):
    report.build(frame(), {"run_id": "r"}, tmp_path)  # case "c" is no adversarial case
    assert "No root finder ran on an adversarial case" in (tmp_path / "report.html").read_text()
    report.build(pd.concat([frame(), _stability_rows()], ignore_index=True), {"run_id": "r"}, tmp_path / "b")
    sec = (tmp_path / "b" / "report.html").read_text()
    assert "run&#x27;s own rows" in sec and "1/2 families survived" in sec


def test_report_with_an_unreadable_stability_stage_says_so(tmp_path):
    (tmp_path / report.STABILITY_DIR).mkdir()
    (tmp_path / report.STABILITY_DIR / "results.csv").write_text("garbage,\n1,2,3\n")
    report.build(pd.concat([frame(), _stability_rows()], ignore_index=True), {"run_id": "r"}, tmp_path)
    html = (tmp_path / "report.html").read_text()
    assert "the stability stage could not be read" in html and "1/2 families survived" in html


def test_compile_table_splits_cold_and_warm_per_backend():
    """The report's compile section: per backend, configurations whose kernel was compiled in the
    run (cold) apart from those that reused one (warm), and those whose backend does not say."""
    rows = [("jax:cpu", "a", "compiled", 2.0), ("jax:cpu", "b", "reused", 0.5), ("jax:cpu", "c", "reused", 0.25),
            ("numpy", "a", None, 0.0)]
    df = pd.DataFrame([{"case_id": "c", "method": "m", "dtype": "float64", "backend": b, "knob": k, "quantity": "depth",
                        "outcome": "ok", "compile_cache": cc, "compile_s": s} for b, k, cc, s in rows])
    t = tables.compile_table(df).set_index(["backend", "kernel"])
    assert t.loc[("jax:cpu", "compiled (cold)"), "configurations"] == 1
    assert t.loc[("jax:cpu", "reused (warm)"), "configurations"] == 2
    assert t.loc[("jax:cpu", "reused (warm)"), "compile total [s]"] == 0.75
    assert t.loc[("jax:cpu", "reused (warm)"), "max [s]"] == 0.5
    assert t.loc[("numpy", "not stated"), "configurations"] == 1


def test_log_axis_labels_are_plain_unicode_not_mathtext():
    """matplotlib's log-axis labels, rewritten without mathtext (bench/report/plots.py:
    PlainLogFormatter), on the ticks matplotlib chose: decades, minor ticks on a short axis, base 2."""
    assert plots.plain_tick_label(r"$\mathdefault{10^{-8}}$") == "10⁻⁸"
    assert plots.plain_tick_label(r"$\mathdefault{2\times10^{-3}}$") == "2×10⁻³"
    assert plots.plain_tick_label(r"$\mathdefault{2^{5}}$") == "2⁵"
    fractional = r"$\mathdefault{10^{2.50}}$"
    assert plots.plain_tick_label(fractional) == fractional  # not rewritten where it could not be exact
    fig, ax = plt.subplots()
    ax.plot([1.5e-3, 4e-3], [1e-12, 1e-3])  # x: less than a decade, so minor ticks get labels
    ax.set_xscale("log")
    plots._finish(fig, ax, "time", "error", "", "t")
    fig.canvas.draw()
    x = [t.get_text() for t in ax.get_xticklabels(minor=True) + ax.get_xticklabels() if t.get_text()]
    y = [t.get_text() for t in ax.get_yticklabels() if t.get_text()]
    plt.close(fig)
    assert any("×10⁻³" in s for s in x), x
    assert "10⁻⁶" in y, y
    assert not any("$" in s for s in x + y)


def _fig_jobs(tmp_path, n):
    series = [{"method": "m", "backend": "numpy", "knob": "n", "fixed": "{}", "x": [1.0, 2.0, 4.0],
               "error": [1e-2, 1e-3, 1e-4], "rate": 3.3}]
    return [("conv", f"t{i}", (series, "depth", "scene units", "error_max"), tmp_path / f"plots/c{i}.png")
            for i in range(n)]


def test_figures_are_drawn_even_where_the_worker_pool_cannot_start_or_breaks(tmp_path, monkeypatch):
    """start_rendering draws in a worker pool where it can (spawned processes: the real one runs
    here too); a pool that cannot start (OSError) or breaks (a worker dies) costs no figure:
    collect() draws the rest here."""
    import concurrent.futures

    monkeypatch.setattr(plots, "POOL_FROM", 1)
    monkeypatch.setattr("bench.run.environment.usable_cores", lambda: 2)

    def no_pool(*a, **k):
        raise OSError("no processes here")

    class BrokenPool:
        def __init__(self, *a, **k):
            pass

        def submit(self, fn, job):
            f = concurrent.futures.Future()
            f.set_exception(concurrent.futures.process.BrokenProcessPool("a worker died"))
            return f

        def shutdown(self, **k):
            pass

    for pool in (concurrent.futures.ProcessPoolExecutor, no_pool, BrokenPool):  # the real pool first
        monkeypatch.setattr(concurrent.futures, "ProcessPoolExecutor", pool)
        jobs = _fig_jobs(tmp_path / pool.__name__, 2)
        pngs = plots.start_rendering(jobs)()
        assert len(pngs) == 2 and all(p.startswith(b"\x89PNG") for p in pngs)
        assert all(path.read_bytes() == p for (_, _, _, path), p in zip(jobs, pngs))


def test_report_figures_are_filled_in_after_the_tables(tmp_path):
    """build() makes the document with placeholders while the figures draw, then fills them in:
    every figure block of the written report holds its PNG."""
    from bench.report import document as doc_mod

    jobs = _fig_jobs(tmp_path, 3)
    rels = [str(p.relative_to(tmp_path)) for *_, p in jobs]
    doc = doc_mod.Document("t", [doc_mod.Figures(tuple(doc_mod.Figure(f"t{i}", None, r) for i, r in enumerate(rels)))])
    pngs = dict(zip(rels, plots.start_rendering(jobs)()))
    with pytest.raises(ValueError, match="would be lost"):  # a drawn figure that no block holds
        doc_mod.fill_figures(doc, {**pngs, "plots/elsewhere.png": b"\x89PNG"})
    doc_mod.fill_figures(doc, pngs)
    (block,) = doc.blocks
    assert [f.path for f in block.items] == rels and all(f.png.startswith(b"\x89PNG") for f in block.items)


def test_html_tables_keep_words_and_numbers_whole_and_scroll_instead():
    """A cell breaks inside a word only where the word alone exceeds the column's width
    (``overflow-wrap: break-word``, not ``anywhere``, which split "float64" and "0.0281" to fit the
    page), a number never (at its exponent's sign either), and a table wider than the page scrolls
    in its own box; the cells' text stays as it was."""
    from bench.report import document

    frame = pd.DataFrame({"dtype": ["float64"], "error": [6.9e-07], "n": [1024], "statuses": ["CONVERGED 756 · MISS 268"]})
    doc = document.Document("t", (document.Table(frame),))
    page = document.to_html(doc)
    assert "anywhere" not in page and "overflow-wrap:break-word" in page
    assert "<div class='scroll'><table" in page
    assert "<td class='n'>6.9e-07</td>" in page and "<td class='n'>1024</td>" in page
    assert "<td>float64</td>" in page and "<td>CONVERGED 756 · MISS 268</td>" in page
    assert "td.n{white-space:nowrap}" in page


def test_best_accuracy_says_why_a_row_has_no_finite_error():
    """The best-accuracy table's error is a number, or says why there is none: which wrong or
    missing answers made it infinite (how many of each), or that no ray was checked."""
    text = tables.error_text
    assert text({"error_max": 3.14159e-12}) == "3.14e-12"
    assert text({"error_max": float("inf"), "n_false_hit": 0, "n_false_miss": 30, "n_miss_declined": 30,
                 "n_converged_nonfinite": 0}) == "inf: 30 hitting ray(s) flagged"
    assert text({"error_max": float("inf"), "n_false_hit": 2, "n_false_miss": 5, "n_miss_declined": 1,
                 "n_converged_nonfinite": 3}) == ("inf: 2 false hit(s), 4 silent miss(es), 3 CONVERGED non-finite, "
                                                  "1 hitting ray(s) flagged")
    assert text({"error_max": float("inf"), "n_false_hit": float("nan")}) == "inf"
    # the error of the answers given: a wrong CONVERGED depth beside flagged rays must not read like a right one
    assert text({"error_max": float("inf"), "n_false_miss": 32, "n_miss_declined": 32, "error_max_finite": 0.51}) == \
        "inf: 32 hitting ray(s) flagged; 0.51 on the rest"
    # rays the reference flags are in no error: the text says how many (it read as the error over every ray)
    assert text({"error_max": 4.02e-7, "n_not_judged": 484}) == "4.02e-07 (484 ray(s) not judged: the reference flags them)"
    assert text({"error_max": float("nan"), "n_declined": 756.0}) == "none: no ray answered (756 declined)"
    assert text({"error_max": float("nan"), "n_declined": float("nan")}) == "none: no ray checked (see its statuses)"
    # and the table takes it, the most accurate setting first
    rows = [{"case_id": "c", "method": "hybrid_secant", "quantity": "depth", "dtype": "float64", "backend": "numpy",
             "knob": f"xtol={x}", "outcome": "ok", "error_max": e, "time_median_s": 1e-3, "time_iqr_s": 1e-4,
             "time_ratio_cf": 1.0, "compile_s": 0.0, "evals_per_ray": 3.0, "status_counts": '{"CONVERGED": 4}',
             "n_false_hit": 0, "n_false_miss": 0, "n_miss_declined": 0, "n_converged_nonfinite": 0}
            for x, e in (("1e-4", 2e-5), ("1e-12", float("inf")))]
    t = tables.summary_table(pd.DataFrame(rows))
    assert t["best max error"].tolist() == ["2e-05"]
