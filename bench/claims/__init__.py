"""The claims ledger: each claim of the lecture checked numerically, with a verdict and evidence.

Contract used by ``bench/commands/claims.py`` (``python -m bench claims``) and by ``bench run`` (a section of
the main report): ``run_claims(out_dir, quick=True, only=None) -> pandas.DataFrame`` writes
``claims.csv`` (one row per claim) and one ``claim_<id>.png`` per claim into ``out_dir``.

Each claim lives in its own module ``c<NN>_<topic>.py`` and registers itself in
:data:`ledger.LEDGER`; :mod:`.ledger` holds the record types and the single verdict rule;
:mod:`.adapters` is the one place where pieces owned by ``reference/`` and ``impls/`` are
obtained.
"""

from __future__ import annotations

import importlib
import time
import traceback
from pathlib import Path

from ..run import interrupts
from ..run.results import write_atomic
from ..run.timing import Timeout, time_limit
from .ledger import (LEDGER, CheckContext, Claim, DuplicateClaimId, Evidence, Ledger, Trial, Verdict, decide,
                     format_numbers, numbers_json)

__all__ = ["run_claims", "claim_ids", "Claim", "Evidence", "Trial", "Verdict", "Ledger", "LEDGER", "CheckContext", "decide",
           "COLUMNS"]

#: claim modules, in report order; each registers its claims on import
CLAIM_MODULES = (
    "c01_boolean",
    "c02_normals",
    "c03_curvature",
    "c04_lipschitz",
    "c05_sphere_tracing",
    "c06_root_orders",
    "c07_implicit_dt",
    "c08_volume_limit",
    "c09_volume_bound",
    "c10_speed_accuracy",
    "c11_diff_tracing",
    "c12_marching_cubes",
)

COLUMNS = ["id", "statement", "equation", "scope", "how_checked", "verdict", "conditions", "counterexample",
           "out_of_scope", "key_numbers", "plot", "n_trials", "n_hold", "seconds", "message"]

_LOADED = False


def _load(ledger: Ledger) -> None:
    """Import every claim module; a module that fails to import becomes an ``error`` claim."""
    global _LOADED
    if _LOADED:
        return
    _LOADED = True
    for name in CLAIM_MODULES:
        try:
            importlib.import_module(f"{__name__}.{name}")
        except DuplicateClaimId as exc:  # neither claim stands for the id: it is an error row, saying why
            ledger.void(exc.id, f"{exc}: neither is checked")
            _broken_module(ledger, name, f"import of bench.claims.{name} stopped: {exc}")
        except Exception as exc:  # never kill the ledger because one module is broken
            _broken_module(ledger, name, f"import of bench.claims.{name} failed: {type(exc).__name__}: {exc}")


def _broken_module(ledger: Ledger, name: str, msg: str) -> None:
    def broken(ctx, _msg=msg):
        raise RuntimeError(_msg)

    ledger.add(Claim(id=name, statement=f"(module {name})", equation="", how_checked="", check=broken))


#: a claim check's time limit (a guard against a hang: the quick checks take ≤ 10 s each on a
#: 2-core machine, the full ones minutes), by mode
CLAIM_TIMEOUT_S = {True: 600.0, False: 3600.0}


def run_one(claim: Claim, out_dir: Path, ctx: CheckContext, timeout_s: float | None = None) -> dict:
    """Run one claim's check; whatever it raises (``SystemExit`` and its own ``BaseException``
    included, and a run past ``timeout_s``, default :data:`CLAIM_TIMEOUT_S`) becomes a row with
    verdict ``error`` and its message.  Once the verdict is decided, a failure to write its key
    numbers or figure is noted in the message and leaves the verdict as decided."""
    timeout_s = CLAIM_TIMEOUT_S[bool(ctx.quick)] if timeout_s is None else timeout_s
    from .figures import message_png, save_png

    plot = f"claim_{claim.id}.png"
    row = {"id": claim.id, "statement": claim.statement, "equation": claim.equation, "scope": claim.scope,
           "how_checked": claim.how_checked, "plot": plot, "out_of_scope": ""}
    t0 = time.perf_counter()
    try:
        with time_limit(timeout_s, "the claim's time limit"):
            ev = claim.check(ctx)
            if not isinstance(ev, Evidence):
                raise TypeError(f"check of claim {claim.id} returned {type(ev).__name__}, expected Evidence")
            d = decide(ev.trials)
    except BaseException as exc:  # the check could not run: error (a Ctrl-C still stops)
        if not (isinstance(exc, Timeout) or interrupts.is_fault(exc)):
            raise
        tb = traceback.format_exc(limit=6)
        row.update(verdict=Verdict.ERROR.value, conditions="", counterexample="", key_numbers="{}", n_trials=0,
                   n_hold=0, message=f"{type(exc).__name__}: {exc}")
        _quietly(lambda: message_png(out_dir / plot, f"claim {claim.id}: error", tb))
        row["seconds"] = round(time.perf_counter() - t0, 3)
        return row
    # the verdict is decided: what follows (key numbers, the figure) reports it and cannot undo it
    # (a figure that failed to save turned a decided "fails" into "error", its counterexample lost)
    row.update(verdict=d.verdict.value, conditions=d.conditions, counterexample=d.counterexample,
               out_of_scope=d.out_of_scope, n_trials=d.n_trials, n_hold=d.n_hold,
               message=ev.note if d.verdict is not Verdict.ERROR else d.counterexample)
    problems = []
    try:
        row["key_numbers"] = numbers_json(ev.key_numbers)
    except Exception as exc:  # noqa: BLE001 - the check's numbers: reported, not fatal
        row["key_numbers"] = "{}"
        problems.append(f"key numbers could not be written ({type(exc).__name__}: {exc})")
    try:
        if ev.figure is not None:
            save_png(ev.figure, out_dir / plot)
        else:
            message_png(out_dir / plot, f"claim {claim.id}", "no figure: " + (ev.note or d.verdict.value))
    except Exception as exc:  # noqa: BLE001 - the check's figure: reported, not fatal
        problems.append(f"the figure could not be drawn ({type(exc).__name__}: {exc})")
        _quietly(lambda: message_png(out_dir / plot, f"claim {claim.id}", problems[-1]))
    if problems:
        row["message"] = "; ".join(filter(None, [row["message"], *problems]))
    row["seconds"] = round(time.perf_counter() - t0, 3)
    return row


def _quietly(fn) -> None:
    try:
        fn()
    except Exception:  # noqa: BLE001 - pragma: no cover - plotting itself broken
        pass


def claim_ids() -> list[str]:
    """The ids of the lecture's claims, in report order (what ``only`` accepts)."""
    _load(LEDGER)
    return LEDGER.ids()


def write_csv_atomic(df, path: Path) -> None:
    """Write ``df`` as CSV to ``path`` atomically."""
    write_atomic(path, lambda tmp: df.to_csv(tmp, index=False))


def run_claims(out_dir: Path, *, quick: bool = True, only: list[str] | None = None, ledger: Ledger | None = None,
               progress=None, reference_dir: Path | None = None):
    """Check the claims and write ``claims.csv`` and ``claim_<id>.png`` into ``out_dir``.

    quick:    small grids (all claims in well under a minute); ``False`` for the full grids.
    only:     claim ids to run (``None``: all); an unknown id is a ValueError listing the known ones.
    ledger:   the claims to run (default: the lecture's, :data:`LEDGER`; tests pass planted ones).
    progress: optional callable ``(claim_id, row)`` called after each claim.
    reference_dir: where costly reference answers are kept between runs (None: computed each time).

    Returns a pandas DataFrame with the columns :data:`COLUMNS`, one row per claim.
    """
    import pandas as pd

    if ledger is None:
        ledger = LEDGER
        _load(ledger)
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise ValueError(f"out_dir={str(out_dir)!r} is a file; pass a folder for claims.csv and the plots")
    claims = ledger.select(only)
    out_dir.mkdir(parents=True, exist_ok=True)
    ctx = CheckContext(quick=bool(quick), reference_dir=None if reference_dir is None else Path(reference_dir))
    rows = []
    for claim in claims:
        row = run_one(claim, out_dir, ctx)
        rows.append(row)
        # rewrite after every claim: a run that dies keeps what it finished
        write_csv_atomic(pd.DataFrame(rows, columns=COLUMNS), out_dir / "claims.csv")
        if progress is not None:
            progress(claim.id, row)
    df = pd.DataFrame(rows, columns=COLUMNS)
    write_csv_atomic(df, out_dir / "claims.csv")
    return df
