"""The ledger: the record types of a claim check and the one rule that turns evidence into a verdict.

A *claim* is a statement of the lecture with the place it is made (``equation``), its **scope**
(the assumptions the lecture makes and the regime it uses the claim for, in words) and a
``check`` function.  The check does not decide the verdict: it returns :class:`Evidence`, a list
of :class:`Trial` s — one concrete instance of the statement (a scene, a matrix, a parameter
point) with a yes/no outcome measured against a criterion written in ``how_checked`` — plus the
key numbers and a figure.  Each trial also says

* ``in_scope``: whether it lies inside the claim's scope (a trial outside it is shown, never
  counted against the claim);
* ``classes``: the named narrower classes it belongs to (e.g. ``"exact SDFs"``,
  ``"symmetric matrices"``), classes a reader would accept as the claim's true scope;
* ``vacuous``: whether a bound it checks is no tighter than a trivial one (e.g. the largest
  possible colour difference).  A vacuous "holds" says nothing, so it counts as *not holding*.

:func:`decide` applies one rule to every claim, on the trials inside the scope, where a trial
*holds* only if it holds and is not vacuous:

* no trial inside the scope, or no trials at all → ``error``
* every trial holds                              → ``holds``
* some fail, and a named class holds throughout  → ``holds under conditions``: the largest such
  class (most trials) is named, with the first failing trial outside it as the counterexample
* otherwise                                      → ``fails``, the first failing trial the
  counterexample (so a bound that holds only where it is vacuous fails)

So a verdict can only be changed by changing what is measured, never by the check picking it,
and "under conditions" needs a class the check named before it saw the outcome.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import json
import math
from pathlib import Path
from typing import Any, Callable

import numpy as np


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
    in_scope: bool = True
    classes: tuple[str, ...] = ()
    vacuous: bool = False

    def __post_init__(self):
        # a check is code: a verdict is counted only from flags that are truth values ("False" as
        # a string counted as a hold, and "no" as inside the scope)
        for name in ("holds", "in_scope", "vacuous"):
            v = getattr(self, name)
            if not isinstance(v, (bool, np.bool_)):
                raise TypeError(f"Trial({self.condition!r}).{name} must be True or False, got {type(v).__name__} {v!r}")
            object.__setattr__(self, name, bool(v))

    @property
    def informative_hold(self) -> bool:
        """Holds, and not only because the bound checked is trivial."""
        return self.holds and not self.vacuous

    def describe(self) -> str:
        text = self.condition + (" [vacuous: no tighter than the trivial bound]" if self.holds and self.vacuous else "")
        if not self.numbers:
            return text
        return f"{text} ({format_numbers(self.numbers)})"


@dataclasses.dataclass
class Evidence:
    """What a check returns: trials, key numbers for the table, and a matplotlib figure."""

    trials: list[Trial]
    key_numbers: dict[str, Any] = dataclasses.field(default_factory=dict)
    figure: Any = None
    note: str = ""


@dataclasses.dataclass(frozen=True)
class CheckContext:
    """What a check may depend on: the mode and a seed (checks are deterministic); and where costly
    reference answers are kept between runs (``reference_dir``, None: computed every time), which
    changes no result."""

    quick: bool = True
    seed: int = 20211
    reference_dir: Path | None = None


@dataclasses.dataclass(frozen=True)
class Claim:
    """A statement of the lecture and how isobench checks it.

    id:          short stable id (``"4b"``); the plot is ``claim_<id>.png``.
    statement:   the claim in the lecture's words (or as a question, where isobench asks one the lecture
                 leaves open).
    equation:    where the lecture makes it (equation number or slide title).
    how_checked: the experiment and the criterion a trial must meet, with its tolerance.
    check:       ``CheckContext -> Evidence``.
    scope:       the assumptions and regime the verdict is judged in (trials say whether they
                 are inside it).
    """

    id: str
    statement: str
    equation: str
    how_checked: str
    check: Callable[[CheckContext], Evidence]
    scope: str = ""


@dataclasses.dataclass(frozen=True)
class Decision:
    verdict: Verdict
    conditions: str
    counterexample: str
    n_trials: int
    n_hold: int
    out_of_scope: str = ""


def decide(trials: list[Trial]) -> Decision:
    """The verdict rule (see the module docstring); pure function of the trials.

    ``n_trials`` and ``n_hold`` count the trials inside the scope (``n_hold``: informative holds);
    ``out_of_scope`` describes the first trial outside the scope that does not hold, if any."""
    if not trials:
        return Decision(Verdict.ERROR, "", "the check produced no trials", 0, 0)
    inside = [t for t in trials if t.in_scope]
    outside_bad = [t for t in trials if not t.in_scope and not t.informative_hold]
    note = outside_bad[0].describe() if outside_bad else ""
    if not inside:
        return Decision(Verdict.ERROR, "", "no trial lies inside the claim's scope", len(trials), 0, note)
    good = [t for t in inside if t.informative_hold]
    bad = [t for t in inside if not t.informative_hold]
    if not bad:
        return Decision(Verdict.HOLDS, "", "", len(inside), len(good), note)
    classes: dict[str, list[Trial]] = {}
    for t in inside:
        for c in t.classes:
            classes.setdefault(c, []).append(t)
    valid = [(c, ts) for c, ts in classes.items() if all(t.informative_hold for t in ts)]
    if valid:
        name, _ = max(valid, key=lambda cv: len(cv[1]))  # the largest class that holds throughout
        counter = next(t for t in bad if name not in t.classes)
        return Decision(Verdict.CONDITIONAL, name, counter.describe(), len(inside), len(good), note)
    return Decision(Verdict.FAILS, "", bad[0].describe(), len(inside), len(good), note)


class DuplicateClaimId(ValueError):
    """Two claims registered under one id: neither may stand for it (the first registered won
    before, silently, and a false claim 9 read "holds" under another module's check)."""

    def __init__(self, claim_id: str, first: str, second: str):
        super().__init__(f"duplicate claim id {claim_id!r}: registered by {first} and by {second}; rename one")
        self.id, self.first, self.second = claim_id, first, second


def _where(claim: Claim) -> str:
    fn = claim.check
    return f"{getattr(fn, '__module__', '?')}.{getattr(fn, '__qualname__', '?')}"


class Ledger:
    """An ordered registry of claims (the default one is :data:`LEDGER`)."""

    def __init__(self) -> None:
        self._claims: dict[str, Claim] = {}

    def add(self, claim: Claim) -> Claim:
        if claim.id in self._claims:
            raise DuplicateClaimId(claim.id, _where(self._claims[claim.id]), _where(claim))
        self._claims[claim.id] = claim
        return claim

    def void(self, claim_id: str, message: str) -> None:
        """Replace claim ``claim_id`` by one whose check fails with ``message`` (an ``error`` row)."""
        old = self._claims[claim_id]

        def broken(ctx, _msg=message):
            raise RuntimeError(_msg)

        self._claims[claim_id] = dataclasses.replace(old, check=broken)

    def claim(self, id: str, *, statement: str, equation: str, how_checked: str, scope: str = ""):
        """Decorator registering ``check(ctx) -> Evidence`` as claim ``id``, judged in ``scope``."""

        def deco(fn: Callable[[CheckContext], Evidence]):
            self.add(Claim(id=id, statement=statement, equation=equation, how_checked=how_checked, check=fn,
                           scope=scope))
            return fn

        return deco

    def parts(self, compute: Callable[[CheckContext], tuple], parts: list[dict]) -> None:
        """Register the parts of a compound claim, each a claim of its own (``parts``: dicts of
        ``id``, ``statement``, ``equation``, ``how_checked``, ``scope``), measured together:
        ``compute(ctx) -> (trials by part id, key numbers, figure)`` runs once per context for all
        of them; the figure goes with the first part."""
        cached = functools.lru_cache(maxsize=2)(compute)
        first = parts[0]["id"]
        for i, part in enumerate(parts):
            def check(ctx, pid=part["id"], lead=i == 0):
                trials, key, fig = cached(ctx)
                return Evidence(trials[pid], key, fig if lead else None, note="" if lead else f"plot: claim_{first}.png")

            self.add(Claim(check=check, **part))

    def ids(self) -> list[str]:
        return list(self._claims)

    def select(self, only: list[str] | None) -> list[Claim]:
        if only is None:
            return list(self._claims.values())
        if isinstance(only, str):
            raise ValueError(f"only must be a list of claim ids, not the string {only!r}; e.g. only=[{only!r}]")
        only = self.expand(only)
        unknown = [i for i in only if i not in self._claims]
        if unknown:
            raise ValueError(f"only: unknown claim id(s) {unknown}; known ids are {self.ids()}")
        return [self._claims[i] for i in dict.fromkeys(only)]  # each once, in the order given

    def expand(self, only: list[str]) -> list[str]:
        """``only`` with a lecture claim's number standing for its parts where it has parts and is
        no id itself: "2" → 2a, 2b, 2c (the README's ``--only 2 7`` was refused once claim 2 was
        split); other ids as given."""
        out = []
        for i in only:
            parts = [k for k in self._claims if str(i).isdigit() and k[:-1] == str(i) and k[-1:].isalpha()]
            out += parts if str(i) not in self._claims and parts else [i]
        return out

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
