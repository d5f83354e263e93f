"""The command line, ``python -m bench COMMAND``: one module here per command.

A command module (any module of this package whose name does not start with ``_``) defines

* ``HELP``: the one-line help ``python -m bench --help`` lists;
* ``add_arguments(parser)``: its arguments, on an :class:`argparse.ArgumentParser`;
* ``run(args) -> int``: the command, given the parsed arguments; returns the exit code;
* optionally ``ORDER`` (an int, default 100): its place in the help, and ``NAME`` (default: the
  module's name, ``_`` read as ``-``).

A new command is a new module here: :func:`main` finds it (``pkgutil``), nothing else changes.
Modules starting with ``_`` hold what commands share.

Exit codes: 0 success; 1 the command ran but its answer is "no": a regression or an incomplete
comparison (``compare``), a run that is incomplete (its ``--budget`` ran out) or in which no
configuration ran (``run``), a claims check that failed (``claims``), a conformance check that
failed (``conformance``); 2 a usage error (a bad argument, an unknown backend, an ``--out`` that
is not new or empty, a run directory another process is writing, a path that cannot be
created), reported as one line ``error: …`` on stderr naming the argument and the fix.  Progress
and summaries go to stdout, as lines when it is not a terminal (a live bar when it is).
"""

from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import sys
from types import ModuleType


def commands() -> list[ModuleType]:
    """The command modules of this package, in help order (``ORDER``, then name)."""
    found = [importlib.import_module(f"{__name__}.{m.name}") for m in pkgutil.iter_modules(__path__)
             if not m.name.startswith("_")]
    return sorted(found, key=lambda mod: (getattr(mod, "ORDER", 100), command_name(mod)))


def command_name(mod: ModuleType) -> str:
    return getattr(mod, "NAME", mod.__name__.rpartition(".")[2].replace("_", "-"))


def parser() -> argparse.ArgumentParser:
    """The parser of ``python -m bench``: one sub-parser per command module."""
    p = argparse.ArgumentParser(prog="python -m bench", description="isobench: verify and time implicit-surface methods")
    sub = p.add_subparsers(dest="cmd", required=True)
    for mod in commands():
        sp = sub.add_parser(command_name(mod), help=mod.HELP)
        mod.add_arguments(sp)
        sp.set_defaults(fn=mod.run)
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        return args.fn(args)
    except BrokenPipeError:  # stdout closed early (`| head`): stop quietly, as a pipe's reader expects
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at exit's flush
        return 1
