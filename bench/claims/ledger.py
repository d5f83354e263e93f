"""The ledger: the record types of a claim check and the one rule that turns evidence into a verdict.

A *claim* is a statement of the lecture with the place it is made (``equation``) and a ``check``
function.  The check does not decide the verdict: it returns :class:`Evidence`, a list of
:class:`Trial` s — one concrete instance of the statement (a scene, a matrix, a parameter
point) with a yes/no outcome measured against a criterion written in ``how_checked`` — plus the
key numbers and a figure.  :func:`decide` applies the same rule to every claim:

* every trial holds                   → ``holds``
* no trial holds                      → ``fails`` (the first failing trial is the counterexample)
* some hold, some fail                → ``holds under conditions`` (the conditions of the trials
  that hold are listed, and the first failing trial is the counterexample)
* the check raised, or gave no trials → ``error`` (with the message)

So a verdict can only be changed by changing what is measured, never by the check picking it.
"""

from __future__ import annotations

import dataclasses
import enum
import json
import math
from typing import Any, Callable


class Verdict(str, enum.Enum):
    HOLDS = "holds"
    CONDITIONAL = "holds under conditions"
    FAILS = "fails"
    ERROR = "error"


@dataclasses.dataclass(frozen=True)
class Trial:
    """One instance of a claim: ``condition`` says what was tried (in words a reader can act on),
    ``holds`` whether the statement was true there by the claim's criterion, ``numbers`` the
    measured values that decided it."""

    condition: str
    holds: bool
    numbers: dict[str, Any] = dataclasses.field(default_factory=dict)

    def describe(self) -> str:
        if not self.numbers:
            return self.condition
        return f"{self.condition} ({format_numbers(self.numbers)})"


@dataclasses.dataclass
class Evidence:
    """What a check returns: trials, key numbers for the table, and a matplotlib figure."""

    trials: list[Trial]
    key_numbers: dict[str, Any] = dataclasses.field(default_factory=dict)
    figure: Any = None
    note: str = ""


@dataclasses.dataclass(frozen=True)
class CheckContext:
    """What a check may depend on: the mode and a seed (checks are deterministic)."""

    quick: bool = True
    seed: int = 20211


@dataclasses.dataclass(frozen=True)
class Claim:
    """A statement of the lecture and how isobench checks it.

    id:          short stable id (``"4b"``); the plot is ``claim_<id>.png``.
    statement:   the claim in the lecture's words (or the issue's, where it asks a question).
    equation:    where the lecture makes it (equation number or slide title).
    how_checked: the experiment and the criterion a trial must meet, with its tolerance.
    check:       ``CheckContext -> Evidence``.
    """

    id: str
    statement: str
    equation: str
    how_checked: str
    check: Callable[[CheckContext], Evidence]


@dataclasses.dataclass(frozen=True)
class Decision:
    verdict: Verdict
    conditions: str
    counterexample: str
    n_trials: int
    n_hold: int


def decide(trials: list[Trial]) -> Decision:
    """The verdict rule (see the module docstring); pure function of the trials."""
    if not trials:
        return Decision(Verdict.ERROR, "", "the check produced no trials", 0, 0)
    good = [t for t in trials if t.holds]
    bad = [t for t in trials if not t.holds]
    counter = bad[0].describe() if bad else ""
    if not bad:
        verdict = Verdict.HOLDS
        conditions = ""
    elif not good:
        verdict = Verdict.FAILS
        conditions = ""
    else:
        verdict = Verdict.CONDITIONAL
        conditions = "; ".join(dict.fromkeys(t.condition for t in good))
    return Decision(verdict, conditions, counter, len(trials), len(good))


class Ledger:
    """An ordered registry of claims (the default one is :data:`LEDGER`)."""

    def __init__(self) -> None:
        self._claims: dict[str, Claim] = {}

    def add(self, claim: Claim) -> Claim:
        if claim.id in self._claims:
            raise ValueError(f"duplicate claim id {claim.id!r}")
        self._claims[claim.id] = claim
        return claim

    def claim(self, id: str, *, statement: str, equation: str, how_checked: str):
        """Decorator registering ``check(ctx) -> Evidence`` as claim ``id``."""

        def deco(fn: Callable[[CheckContext], Evidence]):
            self.add(Claim(id=id, statement=statement, equation=equation, how_checked=how_checked, check=fn))
            return fn

        return deco

    def ids(self) -> list[str]:
        return list(self._claims)

    def select(self, only: list[str] | None) -> list[Claim]:
        if only is None:
            return list(self._claims.values())
        if isinstance(only, str):
            raise ValueError(f"only must be a list of claim ids, not the string {only!r}; e.g. only=[{only!r}]")
        unknown = [i for i in only if i not in self._claims]
        if unknown:
            raise ValueError(f"only: unknown claim id(s) {unknown}; known ids are {self.ids()}")
        return [self._claims[i] for i in only]

    def __len__(self) -> int:
        return len(self._claims)


LEDGER = Ledger()


def _fmt(v: Any) -> str:
    if isinstance(v, bool):
        return str(v)
    if isinstance(v, (int,)) and not isinstance(v, bool):
        return str(v)
    try:
        f = float(v)
    except (TypeError, ValueError):
        return str(v)
    if math.isnan(f) or math.isinf(f):
        return str(f)
    if f == 0 or 1e-3 <= abs(f) < 1e4:
        return f"{f:.4g}"
    return f"{f:.3e}"


def format_numbers(numbers: dict[str, Any]) -> str:
    return ", ".join(f"{k}={_fmt(v)}" for k, v in numbers.items())


def numbers_json(numbers: dict[str, Any]) -> str:
    """Key numbers as a JSON object (floats rounded to 6 significant digits; inf/nan as strings)."""

    def conv(v):
        if isinstance(v, dict):
            return {str(k): conv(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [conv(x) for x in v]
        if isinstance(v, (bool, str)) or v is None:
            return v
        try:
            f = float(v)
        except (TypeError, ValueError):
            return str(v)
        if not math.isfinite(f):
            return str(f)
        if float(f).is_integer() and abs(f) < 2**53 and not isinstance(v, float):
            return int(f)
        return float(f"{f:.6g}")

    return json.dumps(conv(numbers), ensure_ascii=False)
