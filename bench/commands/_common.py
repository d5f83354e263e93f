"""What the command modules share: argument types, the one-line usage error, progress lines,
backend resolution and the user's cases."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..run.environment import ROOT

DEFAULT_REPORTS = ROOT / "reports"

ALLOCATOR_HELP = ("tuned (default): glibc keeps freed memory instead of mmapping and faulting in fresh pages for "
                  "every large temporary (bench.run.environment.tune_allocator; recorded); default: leave malloc alone")


def error(message: str, code: int = 2) -> int:
    """One line on stderr, ``error: …`` (argparse's style and exit code 2 for usage errors)."""
    print(f"error: {message}", file=sys.stderr, flush=True)
    return code


def int_at_least(low: int):
    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        if v < low:
            raise argparse.ArgumentTypeError(f"must be ≥ {low}, got {v}")
        return v

    return parse


def seconds(text: str) -> float:
    """A finite number of seconds ≥ 0."""
    import math

    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not (math.isfinite(v) and v >= 0):
        raise argparse.ArgumentTypeError(f"must be a finite number of seconds ≥ 0, got {text}")
    return v


def share(text: str) -> float:
    """A share in (0, 1] (``--min-comparable``)."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number; give a share in (0, 1], e.g. 0.9") from None
    if not 0 < v <= 1:
        raise argparse.ArgumentTypeError(f"must be a share in (0, 1] (1: every row of BASE), got {text}")
    return v


def json_dict(text: str) -> dict:
    try:
        v = json.loads(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"not valid JSON ({exc}); write e.g. '{{\"xtol\": 1e-8}}'") from None
    if not isinstance(v, dict):
        raise argparse.ArgumentTypeError(f"must be a JSON object of knob → value, got {type(v).__name__}")
    return v


def resolve_backends(ids: list[str], threads: int, flag: str = "--backend", specs: dict | None = None):
    """{id: backend or Unavailable}, each loop driver given ``threads`` worker threads, or an
    error message when an id names nothing (a typo) or two name one backend.  Every backend is
    keyed (and named in rows and reports) by its own ``id``, however it was given: a plug-in's
    ``package.module:attribute`` spec or entry point name, a built-in without its device (``torch``
    is ``torch:cpu``), so that one backend has one name whichever way it is loaded (the registry
    checked a plug-in's id: :func:`impls.registry.id_problem`); an unavailable one, whose id cannot
    be read, by the spec it was given.  ``specs``, when given, receives {id: what to resolve it
    by} for other processes."""
    from impls import registry

    from ..run import interrupts
    from ..run.environment import configure_driver

    backends: dict = {}
    given: dict[str, str] = {}  # id → the spec that named it
    for spec in ids:
        b = registry.resolve(spec)
        key = spec if isinstance(b, registry.Unavailable) else b.id
        if key in backends:
            return None, f"{flag}: {spec!r} and {given[key]!r} both name the backend {key!r}; give one of them"
        backends[key], given[key] = b, spec
    if specs is not None:
        specs.update(given)
    for key, b in list(backends.items()):
        if not isinstance(b, registry.Unavailable):
            try:
                configure_driver(b, threads)
            except BaseException as exc:  # a plug-in's settings or configure(): its fault, not the run's
                if not interrupts.is_fault(exc):
                    raise
                backends[key] = registry.Unavailable(key, f"{given[key]}: configuring its loop driver (settings, "
                                                          f"configure(threads=…)) raised {type(exc).__name__}: {exc}")
    unknown = [b for b in backends.values() if isinstance(b, registry.Unavailable) and b.unknown]
    if unknown:
        return None, f"{flag}: " + "; ".join(b.reason for b in unknown)
    return backends, ""


def write_out_file(out: str, write) -> str:
    """``write(path)`` for a file-valued ``--out``; "" or the error message naming ``--out`` (a
    directory there, a parent that is a file, no permission)."""
    path = Path(out)
    if path.is_dir():
        return f"--out: {path} is a directory; pass a file name"
    try:
        write(path)
    except OSError as exc:
        return f"--out: cannot write {path}: {exc.strerror or exc}; pass a file in a directory you can write"
    return ""


def split(values: list[str] | None) -> list[str] | None:
    if not values:
        return None
    return [v for item in values for v in item.split(",") if v]


def make_console():
    from rich.console import Console

    import os

    return Console(highlight=False, width=None if os.isatty(1) else 200)


class ProgressLines:
    """Progress as plain lines, whatever stdout is (piped, CI, a terminal): one per stage, and
    during the configurations one every ``step`` of them (10 % of the plan or 20, the smaller) and
    at least every ``every_s`` seconds, each with done/total, ok/skipped/failed and the elapsed
    time.  ``periodic=False``: stage lines only (the live bar shows the rest, or --no-progress)."""

    def __init__(self, periodic: bool = True, every_s: float = 30.0):
        import time

        self._clock = time.monotonic
        self.t0 = self._clock()
        self.periodic, self.every_s = periodic, every_s
        self._next, self._last, self.planned = 0, self.t0, False

    def line(self, text: str) -> None:
        print(f"[{self._clock() - self.t0:7.1f} s] {text}", flush=True)

    def __call__(self, i: int, n: int, what: str, counts: dict) -> None:
        if not self.planned:
            self.planned = True
            self.line(f"plan: {n} configurations" + (f", {i} kept from the interrupted run" if i else ""))
            step = max(1, min(20, -(-n // 10)))
            self._next = (i // step + 1) * step
            self._step = step
            return
        now = self._clock()
        if not self.periodic or (i < self._next and now - self._last < self.every_s and i < n):
            return
        while self._next <= i:
            self._next += self._step
        self._last = now
        pct = 100 * i // max(n, 1)
        self.line(f"configurations {i}/{n} ({pct}%): {counts.get('ok', 0)} ok, {counts.get('skipped', 0)} skipped, "
                  f"{counts.get('failed', 0)} failed" + ("" if what == "done" else f"; last: {what[6:86]}"
                                                          if what.startswith("last:") else f"; next: {what[:80]}"))


def load_user_cases(args) -> str | None:
    """Register the cases of ``--cases`` specs and of the ``isobench.cases`` entry points; an
    error message for a bad spec (a broken entry point is a printed warning, not fatal)."""
    from reference import user_cases

    _, errors = user_cases.load_entry_points()
    for e in errors:
        print(f"warning: a case plug-in could not be loaded: {e}", file=sys.stderr, flush=True)
    for spec in split(getattr(args, "cases", None)) or []:
        try:
            user_cases.load(spec)
        except (ValueError, TypeError) as exc:
            return str(exc)
    return None


def configure_process(args) -> dict[str, str]:
    """Threads, caches and allocator of ``bench run``'s options (``--threads``, ``--cache-dir``,
    ``--no-cache``, ``--allocator``), before any array library or backend is imported; returns the
    caches' environment record.  The run's process and its side-stage process call it alike."""
    from ..run.environment import configure_caches, configure_threads, default_cache_dir, tune_allocator

    configure_threads(args.threads)
    record = configure_caches(None if args.no_cache else Path(args.cache_dir) if args.cache_dir else default_cache_dir())
    if args.allocator == "tuned":
        tune_allocator()
    return record


def reference_cache_dir(args) -> Path | None:
    """Where a command keeps costly reference answers: ``<cache dir>/reference`` (None with
    ``--no-cache``, or ``--no-reference-cache`` where the command has it)."""
    from impls.cache import subdir

    return None if getattr(args, "no_reference_cache", False) else subdir("reference")


def run_claims_into(out: Path, *, quick: bool, console, only: list[str] | None = None,
                    reference_dir: Path | None = None) -> str:
    """Call the claims ledger (``bench.claims.run_claims``, the claims ``only`` or all) into
    ``out``, costly reference answers kept in ``reference_dir``; never raises.  Returns a
    one-line note for the report and the console ("" when it worked)."""
    try:
        from ..claims import run_claims

        df = run_claims(out, quick=quick, only=only, reference_dir=reference_dir)
        n = 0 if df is None else len(df)
        console.print(f"claims: {n} checked, ledger in {out / 'claims.csv'}")
        return ""
    except Exception as exc:  # the ledger is a section of the report, never a reason to crash
        note = f"claims failed: {type(exc).__name__}: {exc}"
        console.print(f"[yellow]{note}[/]")
        return note



class UsageError(ValueError):
    """A bad argument or option combination: the command prints it as one ``error: …`` line
    naming the argument and the fix, and exits 2."""
