"""bench/ keeps a shape a newcomer can read: small modules, short functions, commands found from
their modules.

Read from the source with :mod:`ast` (nothing is imported for the size checks): no file under
bench/ longer than :data:`MAX_FILE_LINES` lines, no function or method longer than
:data:`MAX_FUNCTION_LINES` (its ``def`` line to its last line, docstring included).  A module
that outgrows them is split by what its parts do, not by raising the limits.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
BENCH = ROOT / "bench"
MAX_FILE_LINES = 400
MAX_FUNCTION_LINES = 80


def bench_files() -> list[Path]:
    return sorted(BENCH.rglob("*.py"))


def long_functions(path: Path, limit: int = MAX_FUNCTION_LINES) -> list[str]:
    """``name (N lines)`` of every function or method in ``path`` longer than ``limit`` lines."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            start = min([node.lineno] + [d.lineno for d in node.decorator_list])
            n = node.end_lineno - start + 1
            if n > limit:
                out.append(f"{node.name} ({n} lines, from line {start})")
    return out


def test_no_long_file():
    long = {str(p.relative_to(ROOT)): n for p in bench_files()
            if (n := len(p.read_text(encoding="utf-8").splitlines())) > MAX_FILE_LINES}
    assert not long, f"files over {MAX_FILE_LINES} lines (split them by what their parts do): {long}"


def test_no_long_function():
    long = {str(p.relative_to(ROOT)): f for p in bench_files() if (f := long_functions(p))}
    assert not long, f"functions over {MAX_FUNCTION_LINES} lines: {long}"


def test_checker_finds_a_long_function(tmp_path):
    # The checker itself: a planted 81-line method is found, an 80-line function is not.
    body = "\n".join(f"    x{i} = {i}" for i in range(79))
    (tmp_path / "m.py").write_text(f"def short():\n{body}\n\n\nclass C:\n    def long(self):\n"
                                   + "\n".join(f"        y{i} = {i}" for i in range(80)) + "\n")
    assert long_functions(tmp_path / "m.py") == ["long (81 lines, from line 84)"]


def test_help_lists_the_command_modules():
    # python -m bench --help is built from bench/commands/: every module not starting with "_"
    # is a command, with its HELP line.
    from bench import commands

    modules = sorted(p.stem for p in (BENCH / "commands").glob("*.py") if not p.stem.startswith("_"))
    found = commands.commands()
    assert sorted(commands.command_name(m).replace("-", "_") for m in found) == modules
    help_text = commands.parser().format_help()
    for mod in found:
        assert commands.command_name(mod) in help_text
        assert callable(mod.run) and callable(mod.add_arguments) and mod.HELP


@pytest.mark.parametrize("path", bench_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_no_history_in_comments(path):
    # comments and docstrings state why, not which discussion asked for it
    assert "the issue" not in path.read_text(encoding="utf-8").lower()
