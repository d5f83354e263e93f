"""The claims machinery tells a planted true statement from a planted false one.

These tests do not assert the lecture's verdicts (those are the output of a run); they check
that the verdict rule, the error handling and the files behave, on statements whose truth we
know independently.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from bench.claims import COLUMNS, Evidence, Ledger, Trial, Verdict, decide, run_claims
from bench.claims.stats import fit_power


def _planted_ledger() -> Ledger:
    led = Ledger()

    @led.claim("true", statement="sin²x + cos²x = 1", equation="planted", how_checked="|lhs − 1| ≤ 4ε")
    def _true(ctx):
        x = np.linspace(-10, 10, 1001)
        err = np.abs(np.sin(x) ** 2 + np.cos(x) ** 2 - 1)
        return Evidence([Trial(f"x={v:.2f}", bool(e <= 4 * np.finfo(float).eps)) for v, e in zip(x[::100], err[::100])],
                        {"max_err": float(err.max())})

    @led.claim("false", statement="x + 1 < x for all x", equation="planted", how_checked="evaluate")
    def _false(ctx):
        return Evidence([Trial(f"x={v}", bool(v + 1 < v), {"x": v}) for v in (-1.0, 0.0, 2.5)])

    @led.claim("cond", statement="x² ≥ x", equation="planted", how_checked="evaluate on a grid")
    def _cond(ctx):
        xs = np.linspace(-2, 2, 9)
        return Evidence([Trial(f"x={v}", bool(v * v >= v), {"x": v},
                               classes=("x ≤ 0 or x ≥ 1",) if (v <= 0 or v >= 1) else ()) for v in xs])

    @led.claim("rate_true", statement="bisection error halves per step (order 1, ratio 1/2)", equation="planted",
               how_checked="fitted ratio within 0.05 of 1/2")
    def _rate_true(ctx):
        w = 1.0 / 2.0 ** np.arange(1, 30)  # bracket half-widths
        ratio = float(np.exp(np.polyfit(np.arange(w.size), np.log(w), 1)[0]))
        return Evidence([Trial("bracket width", abs(ratio - 0.5) <= 0.05, {"ratio": ratio})])

    @led.claim("rate_false", statement="bisection converges quadratically", equation="planted",
               how_checked="fitted order within 0.1 of 2")
    def _rate_false(ctx):
        e = 1.0 / 2.0 ** np.arange(1, 30)
        q, _ = fit_power(e[:-1], e[1:])
        return Evidence([Trial("bracket width", abs(q - 2) <= 0.1, {"order": q})])

    @led.claim("boom", statement="raises", equation="planted", how_checked="-")
    def _boom(ctx):
        raise ZeroDivisionError("planted failure")

    @led.claim("notevidence", statement="returns junk", equation="planted", how_checked="-")
    def _junk(ctx):
        return 42

    @led.claim("empty", statement="no trials", equation="planted", how_checked="-")
    def _empty(ctx):
        return Evidence([])

    return led


def test_decide_rule():
    t, f = Trial("a", True), Trial("b", False, {"x": 1.0})
    assert decide([t, t]).verdict is Verdict.HOLDS
    d = decide([f, f])
    assert d.verdict is Verdict.FAILS and "b" in d.counterexample and "x=1" in d.counterexample
    # holding somewhere is no condition: without a named class that holds throughout, it fails
    assert decide([t, f]).verdict is Verdict.FAILS
    tc = Trial("a", True, classes=("class A",))
    d = decide([tc, f])
    assert d.verdict is Verdict.CONDITIONAL and d.conditions == "class A" and d.counterexample.startswith("b")
    assert decide([]).verdict is Verdict.ERROR
    assert decide([Trial("o", False, in_scope=False)]).verdict is Verdict.ERROR


def test_planted_bound_that_holds_only_where_vacuous_fails():
    """(a) |sin x − x| ≤ B(x) with B(x) = |x|³/6 + 10·[|x| > 1]: true only where the bound is
    no tighter than the trivial |sin x − x| ≤ |x| + 1."""
    trials = []
    for x in np.linspace(0.1, 3.0, 30):
        err, bound = abs(np.sin(x) - x), (x ** 3 / 6 if x <= 1 else 0.0) + (10.0 if x > 1 else 0.0)
        holds = err <= bound and x > 1  # planted: the informative part (x ≤ 1) is made false
        trials.append(Trial(f"x={x:.2f}", bool(holds), {"err": err, "bound": bound}, vacuous=bound >= x + 1))
    d = decide(trials)
    assert d.verdict is Verdict.FAILS and "x=0.10" in d.counterexample
    # and all-vacuous evidence is no evidence either
    assert decide([t for t in trials if t.vacuous]).verdict is Verdict.FAILS


def test_planted_half_true_compound_claim_fails_in_one_part(tmp_path):
    """(b) "squaring is cheap and exact in float64": the two parts get their own ids."""
    led = Ledger()
    xs = [0.1, 1 / 3, 1e200]

    @led.claim("sq.a", statement="x·x is finite", equation="planted", how_checked="isfinite", scope="x < 1e150")
    def _a(ctx):
        return Evidence([Trial(f"x={x:g}", bool(np.isfinite(x * x)), in_scope=x < 1e150) for x in xs])

    @led.claim("sq.b", statement="x·x is exact", equation="planted", how_checked="x·x == fraction", scope="any x")
    def _b(ctx):
        from fractions import Fraction

        return Evidence([Trial(f"x={x:g}", bool(np.isfinite(x * x)) and Fraction(x * x) == Fraction(x) ** 2) for x in xs])

    df = run_claims(tmp_path, ledger=led).set_index("id")
    assert df.loc["sq.a", "verdict"] == "holds" and "1e+200" in df.loc["sq.a", "out_of_scope"]
    assert df.loc["sq.b", "verdict"] == "fails"
    assert df.loc["sq.a", "scope"] == "x < 1e150"


def test_planted_claim_true_on_a_named_subclass_holds_under_conditions():
    """(c) "‖A‖₂ = max |λ(A)|": true for symmetric matrices, false for a shear."""
    rng = np.random.default_rng(0)
    trials = []
    for k in range(6):
        a = rng.normal(size=(4, 4))
        sym = k % 2 == 0
        a = a + a.T if sym else a
        s, lam = np.linalg.norm(a, 2), np.max(np.abs(np.linalg.eigvals(a)))
        trials.append(Trial(f"matrix {k}", bool(abs(s - lam) <= 1e-12 * s), classes=("symmetric",) if sym else ()))
    trials.append(Trial("shear", bool(np.linalg.norm([[1.0, 1.0], [0.0, 1.0]], 2) == 1.0)))
    d = decide(trials)
    assert d.verdict is Verdict.CONDITIONAL and d.conditions == "symmetric"
    assert "symmetric" not in d.counterexample


def test_planted_true_claim_holds():
    """(d) the triangle inequality, on random vectors."""
    rng = np.random.default_rng(1)
    trials = [Trial(f"pair {k}", bool(np.linalg.norm(a + b) <= np.linalg.norm(a) + np.linalg.norm(b) + 1e-15))
              for k, (a, b) in enumerate(rng.normal(size=(20, 2, 3)))]
    assert decide(trials).verdict is Verdict.HOLDS


def test_planted_claims_get_the_right_verdicts(tmp_path):
    df = run_claims(tmp_path, ledger=_planted_ledger())
    v = dict(zip(df["id"], df["verdict"]))
    assert v == {"true": "holds", "false": "fails", "cond": "holds under conditions", "rate_true": "holds",
                 "rate_false": "fails", "boom": "error", "notevidence": "error", "empty": "error"}
    row = df.set_index("id")
    assert "ZeroDivisionError" in row.loc["boom", "message"] and "planted failure" in row.loc["boom", "message"]
    assert "x=0.5" in row.loc["cond", "counterexample"]
    assert row.loc["cond", "conditions"] == "x ≤ 0 or x ≥ 1"
    assert row.loc["false", "counterexample"].startswith("x=-1.0")


def test_files_written(tmp_path):
    df = run_claims(tmp_path, ledger=_planted_ledger(), only=["true", "boom"])
    assert list(df.columns) == COLUMNS
    on_disk = pd.read_csv(tmp_path / "claims.csv")
    assert list(on_disk["id"]) == ["true", "boom"]
    for p in df["plot"]:
        assert (tmp_path / p).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")], "temp files left behind"


def test_bad_only_is_a_clear_error(tmp_path):
    with pytest.raises(ValueError, match="unknown claim id"):
        run_claims(tmp_path, ledger=_planted_ledger(), only=["nope"])
    with pytest.raises(ValueError, match="list of claim ids"):
        run_claims(tmp_path, ledger=_planted_ledger(), only="true")


def test_out_dir_is_a_file(tmp_path):
    f = tmp_path / "x"
    f.write_text("")
    with pytest.raises(ValueError, match="out_dir"):
        run_claims(f, ledger=_planted_ledger())


def test_markdown_and_terminal_summaries(tmp_path):
    from bench.claims.summary import markdown_section, terminal_summary

    df = run_claims(tmp_path, ledger=_planted_ledger(), only=["true", "cond", "boom"])
    md = markdown_section(df, plot_prefix="claims/")
    assert md.count("\n| ") == 1 + 3  # header + one row per claim
    assert "[png](claims/claim_cond.png)" in md and "holds for: x ≤ 0 or x ≥ 1" in md
    assert "ZeroDivisionError" in md
    lines = terminal_summary(df).splitlines()
    assert len(lines) == 3 and "error" in lines[2]


def _misbehaving_ledger() -> Ledger:
    led = Ledger()

    @led.claim("exits", statement="calls sys.exit", equation="planted", how_checked="-")
    def _exits(ctx):
        raise SystemExit(3)

    class Own(BaseException):
        pass

    @led.claim("own", statement="raises its own BaseException", equation="planted", how_checked="-")
    def _own(ctx):
        raise Own("planted")

    @led.claim("hangs", statement="never returns", equation="planted", how_checked="-")
    def _hangs(ctx):
        import time

        time.sleep(600)

    @led.claim("false_badfig", statement="x + 1 < x", equation="planted", how_checked="evaluate")
    def _false_badfig(ctx):
        return Evidence([Trial("x=0", False, {"x": 0.0})], {"huge": 10 ** 400}, figure="not a figure")

    @led.claim("stringly", statement="holds given as a string", equation="planted", how_checked="-")
    def _stringly(ctx):
        return Evidence([Trial("x=0", "False")])

    @led.claim("after", statement="x = x", equation="planted", how_checked="-")
    def _after(ctx):
        return Evidence([Trial("x=1", True)])

    return led


def test_a_check_that_exits_raises_or_hangs_is_an_error_row_and_the_next_claims_run(tmp_path):
    """Before (the 2026-11-30 claims probe): a check calling sys.exit ended ``bench claims`` with
    exit code 3, no row and no later claim checked; one that hung held the run forever; a figure
    that failed to save turned a decided "fails" into "error", its counterexample lost; and
    ``Trial(holds="False")`` counted as a hold."""
    from bench.claims import run_one
    from bench.claims.ledger import CheckContext

    led = _misbehaving_ledger()
    rows = {c.id: run_one(c, tmp_path, CheckContext(), timeout_s=1.0 if c.id == "hangs" else None)
            for c in led.select(None)}
    v = {k: r["verdict"] for k, r in rows.items()}
    assert v == {"exits": "error", "own": "error", "hangs": "error", "false_badfig": "fails", "stringly": "error",
                 "after": "holds"}, v
    assert "SystemExit" in rows["exits"]["message"] and "Own: planted" in rows["own"]["message"]
    assert "ran past the time limit of 1 s" in rows["hangs"]["message"]
    bad = rows["false_badfig"]
    assert bad["counterexample"].startswith("x=0") and "figure could not be drawn" in bad["message"]
    assert "key numbers could not be written" in bad["message"]
    assert "holds must be True or False" in rows["stringly"]["message"]


def test_a_claim_id_registered_twice_is_an_error_not_the_first_comer():
    """Two modules registering one id: the first won silently, and ``--only 9`` ran a planted
    module's check under the lecture's claim 9, which read "holds".  Now the id is an error row
    naming both, and ``--only`` takes each id once."""
    from bench.claims.ledger import DuplicateClaimId

    led = _planted_ledger()
    with pytest.raises(DuplicateClaimId, match=r"duplicate claim id 'true': registered by .*_true and by .*impostor"):
        @led.claim("true", statement="impostor", equation="-", how_checked="-")
        def impostor(ctx):
            return Evidence([Trial("x", True)])
    led.void("true", "duplicate claim id 'true': neither is checked")
    assert [c.id for c in led.select(["false", "false"])] == ["false"]


def test_a_claims_number_stands_for_its_parts():
    """``--only 2 7`` (the README's example) was refused once claim 2 became 2a, 2b and 2c: a
    number that is no id itself but has lettered parts selects them, in order; ids stay as given."""
    from bench.claims import claim_ids
    from bench.claims.ledger import LEDGER

    claim_ids()  # (loads the ledger)
    assert LEDGER.expand(["2", "7"]) == ["2a", "2b", "2c", "7"]
    assert [c.id for c in LEDGER.select(["2", "2b"])] == ["2a", "2b", "2c"]
    assert LEDGER.expand(["7", "nosuch"]) == ["7", "nosuch"]
    with pytest.raises(ValueError, match="unknown claim id"):
        LEDGER.select(["99"])
