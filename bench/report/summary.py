"""What a reader needs first: the run at a glance and "which to pick".

Pure functions of a results frame (``bench.run.results`` columns) and the run's environment, used
by the report's first screen and by the CLI's closing summary, so both say the same thing.

*Which to pick*: for each method family (root, gradient, param_grad, render), each case and each
error target, the fastest configuration (method × backend × dtype × knob setting) whose max
error over every ray of the case, on the family's primary quantity (depth, normal angle, dt/dθ,
colour against the rendering integral), is at or below the target, with no false hit or miss and
no ray the reference flags (a row with ``n_not_judged`` > 0 was not fully checked and is never
picked; a case without another candidate reads ``not judged``) and no ray it declined (a
failure status: a root finder's uncertified miss counts, a renderer's or gradient's declined
ray too, ``n_declined``); where no configuration answers every ray, one that flagged at most
1 % of them and answered the rest to the target, with the number it flagged
(:data:`FLAGGED_SHARE`).  "Fastest" is the median time in
units of the closed-form ray–sphere intersection of the same rays measured beside its samples
(``time_ratio_cf``), so that cases of different sizes read alike; in an accuracy-only run (no
timing) the cheapest in field evaluations per ray is taken instead, and the table says so.
Comparisons are made within one case only: a method measured on another case is not its
competitor there.
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd

CONFIG_KEY = ["case_id", "backend", "dtype", "method", "knob"]
PICK_NOTE = ("Per method family and case, for each error target: the fastest configuration (method · backend · "
             "dtype @ knobs) whose max error over every ray (the rendering integral: over the rays it is computed on, "
             "n_checked of them) is at or below the target, with no false hit or miss "
             "and no ray the reference flags ('not judged': some rays have no certified reference answer; "
             "'nothing to check': no ray has a reference answer for the quantity, e.g. none hits); "
             "where none answers every ray, the fastest configuration whose only unanswered rays are rays it flagged "
             "(at most 1 % of them; its error over the rays it answered), with the count of flagged rays; "
             "its time as a multiple of the closed-form ray–sphere intersection of the same rays (× closed form) "
             "and its field evaluations per ray. 'untimed': an accuracy-only run, ranked by evaluations.")
#: the pick of a case some of whose rays the reference flags (``n_not_judged``, bench.run.metrics)
NOT_JUDGED = "not judged"
#: the pick of a case where no ray has a reference answer for the family's quantity (every row
#: ``n_checked`` = 0: e.g. dt/dθ of a method that finds its own hits, on a case whose every ray
#: misses), which is not a failure to reach the target
NOTHING_TO_CHECK = "nothing to check"
#: picks that name no configuration
NO_PICK = ("none reached", NOT_JUDGED, NOTHING_TO_CHECK)
#: the error targets every "fastest to target" table uses
TARGETS = (1e-4, 1e-8, 1e-12)
#: where no configuration of a case answers every ray, one whose only unanswered rays are rays
#: it flagged (declined: UNCERTIFIED, MAX_ITER, …; none silently wrong) may still be picked when
#: it flagged at most this share of the case's rays (a certified method flags a few grazing rays,
#: hits and misses alike: 2 of the torus camera's 1,024, 0.2 %, and a table of "none reached"
#: would answer nothing); the pick says how many
FLAGGED_SHARE = 1e-2


def ok_rows(df: pd.DataFrame) -> pd.DataFrame:
    """The measured rows, their numeric columns as floats."""
    ok = df[df["outcome"] == "ok"].copy()
    for c in ("error_max", "time_median_s", "time_iqr_s", "time_ratio_cf", "compile_s", "evals_per_ray"):
        ok[c] = pd.to_numeric(ok[c], errors="coerce") if c in ok else np.nan
    return ok


def knob_label(method: str, knob: str) -> str:
    """``knob`` (a :func:`bench.run.results.knob_string`) without the settings that are the method's
    defaults, so that a table shows what was chosen: ``xtol=1e-08`` rather than all eight knobs
    of ``hybrid_secant``; ``defaults`` when every knob is at its default, ``""`` for a method
    without knobs, and the whole string for a method the catalog does not know."""
    from impls.methods import METHODS

    from ..run.results import knob_string

    spec = METHODS.get(method)
    if not knob or spec is None:
        return knob
    default = set(knob_string({k.name: k.default for k in spec.knobs}).split(","))
    chosen = [kv for kv in knob.split(",") if kv not in default]
    return ",".join(chosen) or "defaults"


def config_counts(df: pd.DataFrame) -> dict[str, int]:
    """Planned configurations by outcome: ``ran`` (a quantity measured), ``failed``, ``skipped``."""
    if df is None or not len(df):
        return {"ran": 0, "skipped": 0, "failed": 0}
    rank = df["outcome"].map({"ok": 0, "failed": 1, "skipped": 2}).fillna(3)
    first = df.assign(_rank=rank).sort_values("_rank").groupby(CONFIG_KEY, sort=False)["outcome"].first()
    counts = first.value_counts()
    return {"ran": int(counts.get("ok", 0)), "skipped": int(counts.get("skipped", 0)),
            "failed": int(counts.get("failed", 0))}


def failures(df: pd.DataFrame, limit: int = 10) -> list[str]:
    """The first ``limit`` failed configurations as ``case backend dtype method @ knobs: reason``
    lines (the knobs where it has any: the points of one method's sweep fail apart)."""
    if df is None or not len(df):
        return []
    bad = df[df["outcome"] == "failed"].drop_duplicates(CONFIG_KEY)
    return [f"{r.case_id} {r.backend} {r.dtype} {r.method}{_at_knobs(r.knob)}: {str(r.reason)[:160]}"
            for r in bad.head(limit).itertuples(index=False)]


def _at_knobs(knob) -> str:
    return f" @ {knob}" if isinstance(knob, str) and knob else ""


def overview(df: pd.DataFrame, env: dict) -> dict[str, str]:
    """Run, suite, commit, machine and completeness, as label → text."""
    c = config_counts(df)
    return {
        "run": str(env.get("run_id", "?")),
        "suite": str(env.get("suite", "?")),
        "commit": str(env.get("git_commit", env.get("commit", "?")))[:12],
        "machine": " · ".join(str(env[k]) for k in ("cpu", "platform") if env.get(k)) or str(env.get("machine", "?")),
        "configurations": f"{c['ran']} ran · {c['skipped']} skipped · {c['failed']} failed",
        "complete": "yes" if str(env.get("complete", "true")) == "true" else
                    f"NO — {env.get('incomplete_reason', 'the run stopped before its plan was done')}",
    }


def _primary(ok: pd.DataFrame) -> pd.DataFrame:
    """Rows of each method's primary quantity (the family's main answer), or, for a family and
    case where that quantity was not measured (the quick suite checks renderers against the
    surface image, ρ(x*) and 0 at misses, not the costly rendering integral), of the quantity that
    was, named in the ``case`` column."""
    from impls.methods import METHODS

    from ..run.metrics import primary_quantity

    want = {m: primary_quantity(s) for m, s in METHODS.items()}
    is_primary = ok["quantity"] == ok["method"].map(want).fillna(ok["quantity"])
    have = set(zip(ok.loc[is_primary, "family"], ok.loc[is_primary, "case_id"]))
    fallback = ~is_primary & pd.Series([(f, c) not in have for f, c in zip(ok["family"], ok["case_id"])], index=ok.index)
    out = ok[is_primary | fallback].copy()
    named = fallback[is_primary | fallback]
    out.loc[named, "case_id"] = out.loc[named, "case_id"] + " · " + out.loc[named, "quantity"]
    return out


def which_to_pick(df: pd.DataFrame, targets=TARGETS) -> pd.DataFrame:
    """Per family × case × target: the fastest configuration reaching the target (module doc).

    Columns: family, case, target, pick (``method · backend · dtype``), knob, ``× closed form``,
    ``time [ms]``, ``evals/ray``, ``by`` (``time`` or ``evals`` when the run was untimed),
    ``candidates`` (configurations that reached the target).  A target no configuration reached
    is a row with pick ``none reached`` and the best error seen.  Rows with rays the reference flags
(``n_not_judged`` > 0, :func:`bench.run.metrics.judged_rays`) are never candidates; a case with such
rows and no other candidate gets pick ``not judged`` and the number of flagged rays; a case
where no row checked any ray (``n_checked`` 0: no ray has a reference answer for the quantity)
gets ``nothing to check``.  Where no
configuration answers every ray (``n_declined`` = 0, no false hit or miss), one whose only
unanswered rays are rays it flagged itself (``n_false_miss`` = ``n_miss_declined``,
``n_declined`` at most :data:`FLAGGED_SHARE` of the rays, no false hit) and whose answered rays
reach the target (``error_max_finite``) is picked, column ``flagged`` giving the count."""
    ok = ok_rows(df)
    if ok.empty:
        return pd.DataFrame(columns=["family", "case", "target", "pick", "knob", "× closed form", "time [ms]",
                                     "evals/ray", "by", "candidates"])
    ok = _primary(ok)
    for c in ("n_false_hit", "n_false_miss", "n_not_judged"):
        ok[c] = pd.to_numeric(ok[c], errors="coerce").fillna(0) if c in ok else 0
    for c in ("n_rays", "error_max_finite"):
        ok[c] = pd.to_numeric(ok[c], errors="coerce") if c in ok else np.nan
    ok["n_miss_declined"] = pd.to_numeric(ok["n_miss_declined"], errors="coerce").fillna(0) if "n_miss_declined" in ok \
        else 0
    ok["n_declined"] = _declined_rays(ok)
    # a row with rays the reference flags was not fully checked: never a pick (it could be wrong
    # exactly where nothing judged it); the table says so instead.  Nor is one that declined rays
    # (its error leaves them out): "every ray" means answered, not skipped
    clean = ok[(ok["n_false_hit"] == 0) & (ok["n_false_miss"] == 0) & (ok["n_not_judged"] == 0)
               & (ok["n_declined"] == 0)]
    # the fallback (FLAGGED_SHARE): every wrong-looking miss is a ray the method flagged, few rays
    # flagged in all; its error is then the one over the rays it answered (error_max_finite, or the
    # max error where no answer was wrong: a gradient's or renderer's declined rays are left out of it)
    ok["error_answered"] = ok["error_max_finite"].where(~np.isfinite(ok["error_max"]), ok["error_max"])
    silent_nan = pd.to_numeric(ok["n_converged_nonfinite"], errors="coerce").fillna(0) \
        if "n_converged_nonfinite" in ok else 0
    flagging = ok[(ok["n_false_hit"] == 0) & (ok["n_not_judged"] == 0) & (ok["n_declined"] > 0) & (silent_nan == 0)
                  & (ok["n_false_miss"] == ok["n_miss_declined"])
                  & (ok["n_declined"] <= FLAGGED_SHARE * ok["n_rays"])]
    rows = []
    for (fam, cid), g in ok.groupby(["family", "case_id"], sort=True):
        gc = clean[(clean["family"] == fam) & (clean["case_id"] == cid)]
        gf = flagging[(flagging["family"] == fam) & (flagging["case_id"] == cid)]
        unjudged = int(g["n_not_judged"].max())
        checked = pd.to_numeric(g["n_checked"], errors="coerce") if "n_checked" in g else pd.Series([np.nan])
        # (a row that checked 0 rays because it declined them all had something to check)
        nothing = bool((checked == 0).all()) and not bool((g["n_declined"] > 0).any())
        # (of every measured row of the case: where no row answers every ray, the fallback's are timed too)
        timed = bool(np.isfinite(g["time_ratio_cf"]).any())
        by = "time_ratio_cf" if timed else "evals_per_ray"
        for tgt in targets:
            cands, flagged = gc[gc["error_max"] <= tgt], False
            if cands.empty:  # the fallback: few flagged rays, the answered ones at the target
                cands, flagged = gf[gf["error_answered"] <= tgt], True
            cands = cands[np.isfinite(cands[by])] if timed else cands
            row = {"family": fam, "case": cid, "target": tgt, "by": "time" if timed else "evals",
                   "candidates": int(len(cands))}
            if not cands.empty:
                r = cands.sort_values([by, "evals_per_ray", "time_median_s"], na_position="last").iloc[0]
                row.update({"pick": f"{r['method']} · {r['backend']} · {r['dtype']}",
                            "knob": knob_label(r["method"], r["knob"]),
                            "× closed form": r["time_ratio_cf"], "time [ms]": 1e3 * r["time_median_s"],
                            "evals/ray": r["evals_per_ray"], **({"flagged": int(r["n_declined"])} if flagged else {})})
            elif unjudged:
                row.update({"pick": NOT_JUDGED, "knob": f"{unjudged} ray(s) the reference flags: no configuration "
                                                        "is fully checked"})
            elif nothing:
                row.update({"pick": NOTHING_TO_CHECK, "knob": "no ray of the case has a reference answer for this "
                                                              "quantity (e.g. no ray hits)"})
            else:
                row.update({"pick": "none reached", "knob": _why_none(g)})
            rows.append(row)
    return pd.DataFrame(rows)


def _declined_rays(ok: pd.DataFrame) -> pd.Series:
    """Per row, the rays it declined (``n_declined``: flagged with a failure status, left
    unanswered; bench.run.metrics); a root row from a run before root rows counted them
    (2026-11-30) has only its flagged hitting rays, ``n_miss_declined``."""
    d = pd.to_numeric(ok["n_declined"], errors="coerce") if "n_declined" in ok else pd.Series(np.nan, index=ok.index)
    return d.fillna(ok["n_miss_declined"]).fillna(0)


def _why_none(g: pd.DataFrame) -> str:
    """Why no configuration of a case reached a target: the best error seen where one is finite;
    else whether some configuration's only unanswered hits are rays it flagged itself (every
    ``n_false_miss`` a ``n_miss_declined``, no false hit: nothing wrong, too many flagged for
    :data:`FLAGGED_SHARE` or its answered rays above the target) or every one gave a wrong answer."""
    best = g.loc[g["n_declined"] == 0, "error_max"].min()  # (a row that declined rays has no error over every ray)
    if np.isfinite(best):
        return f"best error {best:.2g}"
    silent_nan = pd.to_numeric(g["n_converged_nonfinite"], errors="coerce").fillna(0) if "n_converged_nonfinite" in g \
        else 0
    honest = g[(g["n_false_hit"] == 0) & (g["n_false_miss"] == g["n_miss_declined"]) & (g["n_declined"] > 0)
               & (silent_nan == 0)]
    if honest.empty:
        return "every configuration had a false hit or miss or a non-finite depth"
    r = honest.sort_values(["n_declined", "error_answered"], na_position="last", kind="stable").iloc[0]
    answered = f", error {r['error_answered']:.2g} on the rays it answered" if np.isfinite(r["error_answered"]) \
        else ""
    of = f" of {int(r['n_rays'])}" if np.isfinite(r["n_rays"]) else ""
    # (no parentheses: the headline puts this text in some)
    return (f"every configuration left rays unanswered; the fewest flagged: {int(r['n_declined'])}{of}, "
            f"by {r['method']} · {r['backend']} · {r['dtype']}, with no false hit or miss{answered}; a pick may "
            f"flag at most {FLAGGED_SHARE:.1%}")


def _flagged_text(d: dict) -> str:
    """``; N ray(s) flagged`` for a pick made among configurations that flagged rays (FLAGGED_SHARE)."""
    n = d.get("flagged")
    return f"; {int(n)} ray(s) flagged" if n is not None and np.isfinite(n) and n > 0 else ""


def headline(picks: pd.DataFrame, target: float = 1e-8) -> list[str]:
    """One line per family at ``target``: the pick on each case, e.g.
    ``root ≤ 1e-08: sphere.camera.64x64 → hybrid_secant · jax:cpu · float64 (×7.1, 3.6 evals/ray)``."""
    if picks is None or picks.empty:
        return []
    lines = []
    for fam, g in picks[picks["target"] == target].groupby("family", sort=True):
        parts = []
        for d in g.to_dict("records"):
            if d["pick"] in NO_PICK:
                parts.append(f"{d['case']} → {d['pick']}")
                continue
            cost = (f"×{d['× closed form']:.3g}, " if d["by"] == "time" else "untimed, ") + f"{d['evals/ray']:.3g} evals/ray"
            parts.append(f"{d['case']} → {d['pick']} ({cost}{_flagged_text(d)})")
        lines.append(f"{fam} ≤ {target:.0e}: " + "; ".join(parts))
    return lines


def status_text(v) -> str:
    """A status histogram (JSON) as ``CONVERGED 3096 · MISS 1000``."""
    try:
        d = json.loads(v) if isinstance(v, str) and v else {}
    except ValueError:
        return str(v)
    return " · ".join(f"{k} {n}" for k, n in sorted(d.items(), key=lambda kv: -kv[1]))


def pick_grid(picks: pd.DataFrame) -> pd.DataFrame:
    """``which_to_pick`` as one row per family × case and one column per target, each cell
    ``method · backend · dtype (×ratio, evals/ray)`` or ``none reached``."""
    if picks is None or picks.empty:
        return pd.DataFrame(columns=["family", "case"])
    rows: dict[tuple, dict] = {}
    for d in picks.to_dict("records"):
        row = rows.setdefault((d["family"], d["case"]), {"family": d["family"], "case": d["case"]})
        if d["pick"] in NO_PICK:
            cell = f"{d['pick']} ({d['knob']})"
        else:
            cost = f"×{d['× closed form']:.3g}" if d["by"] == "time" else "untimed"
            knob = f" @ {d['knob']}" if d["knob"] and d["knob"] != "defaults" else ""
            cell = f"{d['pick']}{knob} ({cost}, {d['evals/ray']:.3g} evals/ray{_flagged_text(d)})"
        row[f"≤ {d['target']:.0e}"] = cell
    return pd.DataFrame(list(rows.values()))


def clip_words(text: str, width: int) -> str:
    """``text`` of at most ``width`` characters: whole, or cut at the last space before the limit
    with "…" (a word is never cut in half; one longer than the limit is)."""
    text = str(text)
    if len(text) <= width:
        return text
    head = text[:width - 1]
    cut = head.rsplit(" ", 1)[0] if " " in head else head
    return cut.rstrip(" ,;:") + "…"


def claims_lines(claims: pd.DataFrame | None) -> pd.DataFrame:
    """One line per claim, failures first: id, verdict, statement (short), scope (short); the
    full texts are in the claims ledger."""
    if claims is None or not len(claims):
        return pd.DataFrame(columns=["id", "verdict", "statement"])
    order = {"fails": 0, "error": 1, "holds under conditions": 2, "holds": 3}
    c = claims.assign(_r=claims["verdict"].map(order).fillna(1)).sort_values("_r", kind="stable")
    out = pd.DataFrame({"id": c["id"], "verdict": c["verdict"],
                        "statement": [clip_words(t, 110) for t in c["statement"]]})
    if "conditions" in c:
        out["holds on / counterexample"] = [
            clip_words(f"holds on: {r['conditions']}" if r["verdict"] == "holds under conditions" else
                       str(r.get("counterexample", "")) if r["verdict"] == "fails" else "", 160)
            for _, r in c.iterrows()]
    return out


def first_screen(df: pd.DataFrame, env: dict, *, claims: pd.DataFrame | None = None,
                 scoreboard: list[str] | None = None, regressions: pd.DataFrame | None = None) -> dict:
    """What the report shows first, in this order: the run (:func:`overview`), failures, the
    regressions against a baseline (when given), "which to pick" (:func:`pick_grid`), the
    stability scoreboard (one line per backend) and the claims' verdicts (failures first).
    Returned as named parts (``overview`` dict, ``failures`` list, ``regressions`` frame or None,
    ``picks`` frame, ``scoreboard`` list, ``claims`` frame) for the Markdown, HTML and terminal
    renderings."""
    picks = which_to_pick(df) if df is not None and len(df) else pd.DataFrame()
    return {"overview": overview(df, env), "failures": failures(df), "regressions": regressions,
            "picks": pick_grid(picks), "headline": headline(picks), "scoreboard": list(scoreboard or []),
            "claims": claims_lines(claims)}


def terminal_text(fs: dict, report_path: str = "") -> str:
    """The closing summary of ``bench run``: one screen (about 25 lines)."""
    ov = fs["overview"]
    lines = [f"run {ov['run']} · suite {ov['suite']} · commit {ov['commit']} · {ov['configurations']}"
             + ("" if ov["complete"] == "yes" else f" · INCOMPLETE: {ov['complete'][5:]}")]
    if fs["failures"]:
        lines += ["failed:"] + [f"  {f}" for f in fs["failures"][:5]]
        if len(fs["failures"]) > 5:
            lines.append(f"  … {len(fs['failures']) - 5} more in the report")
    reg = fs.get("regressions")
    if reg is not None:
        lines.append(f"regressions against the baseline: {len(reg)}")
        lines += [f"  {r}" for r in reg.head(5).astype(str).agg(" ".join, axis=1)]
    if fs["headline"]:
        lines += ["which to pick:"] + [f"  {h[:200]}" for h in fs["headline"]]
    if fs["scoreboard"]:
        lines += ["stability:"] + [f"  {s}" for s in fs["scoreboard"]]
    cl = fs["claims"]
    if len(cl):
        counts = cl["verdict"].value_counts()
        lines.append("claims: " + " · ".join(f"{v} {counts[v]}" for v in counts.index)
                     + ("; failing: " + ", ".join(cl[cl["verdict"] == "fails"]["id"].astype(str)) if
                        (cl["verdict"] == "fails").any() else ""))
    if report_path:
        lines.append(f"report: {report_path}")
    return "\n".join(lines)
