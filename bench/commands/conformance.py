"""``python -m bench conformance --backend SPEC``: the conformance suite on one backend.

The suite is ``tests/conformance/`` (every method × applicable scene against exact
answers, the evaluation counts, the statuses, float32, agreement with numpy; docs/backends.md).
It runs here through pytest, in this process, with ``SPEC`` added to the suite's backends the
way ``ISOBENCH_EXTRA_BACKENDS`` adds it (tests/conftest.py), and only the checks of that backend
selected.  Each check's outcome is printed (passed, failed with its first line, skipped with
the reason, xfailed with the ``Capabilities.expected_failures`` reason), then the counts.

Exit codes: 0 no check failed and at least one passed; 1 a check failed (an expected failure
that passes counts as failed: ``xfail(strict)``), or none passed (nothing was verified); 2 a
usage error (a spec that names nothing, pytest or the suite not installed).
"""

from __future__ import annotations

import argparse
import os
import sys

from ..run.environment import ROOT
from ._common import error

ORDER = 11
HELP = "run the conformance suite (tests/conformance/) on a backend, e.g. a plug-in"
SUITE = ROOT / "tests" / "conformance"
#: how tests/conftest.py learns of backends beyond the registered ones
EXTRA_ENV = "ISOBENCH_EXTRA_BACKENDS"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--backend", required=True, metavar="SPEC",
                   help="the backend: a registered id (numpy, torch:cpu, …) or a plug-in package.module:attribute")
    p.add_argument("--select", metavar="EXPR", help="only the checks whose names match this pytest -k expression "
                   "(e.g. 'root_depth or evals'); default: every check")
    p.add_argument("--fast", action="store_true", help="leave out the checks marked slow themselves (catalog "
                   "sweeps, many compiled kernels); a compiling backend's other checks still run")


class _Outcomes:
    """A pytest plugin: keeps the checks of one backend, records and prints each outcome."""

    def __init__(self, backend_id: str, fast: bool = False):
        self.backend_id = backend_id
        self.fast = fast
        self.counts = {"passed": 0, "failed": 0, "skipped": 0, "xfailed": 0}
        self.not_offered: dict[str, int] = {}  # skip reason → checks: one line each at the end

    def _ours(self, item) -> bool:
        params = getattr(getattr(item, "callspec", None), "params", {})
        return params.get("any_backend") == self.backend_id or params.get("backend") == self.backend_id

    @staticmethod
    def _slow_itself(item) -> bool:
        """Marked slow by the check itself, not only by its backend parameter.

        tests/conftest.py marks every check of a compiling backend (jax, numba) slow, so that
        ``pytest -m "not slow"`` runs the eager backends only; ``--fast`` on such a backend must
        still keep its quick checks (``-m "not slow"`` here would keep none of them)."""
        slow = sum(1 for _ in item.iter_markers("slow"))
        from_param = sum(1 for m in getattr(getattr(item, "callspec", None), "marks", ()) if m.name == "slow")
        return slow > from_param

    def pytest_collection_modifyitems(self, session, config, items):
        keep = [it for it in items if self._ours(it) and not (self.fast and self._slow_itself(it))]
        kept = set(map(id, keep))
        config.hook.pytest_deselected(items=[it for it in items if id(it) not in kept])
        items[:] = keep

    def pytest_collectreport(self, report):
        if report.failed:  # the suite itself could not be imported: nothing of the backend was checked
            self.counts["failed"] += 1
            print(f"ERROR    collecting {report.nodeid}: {str(report.longrepr).strip().splitlines()[-1]}", flush=True)

    def pytest_runtest_logreport(self, report):
        if report.when != "call" and not (report.failed or report.skipped):
            return
        name = report.nodeid.rpartition("::")[2]
        if hasattr(report, "wasxfail"):
            outcome = "xfailed" if report.skipped else "failed"
            why = report.wasxfail if report.skipped else f"expected to fail ({report.wasxfail}) but passed"
        elif report.skipped:
            outcome = "skipped"
            why = report.longrepr[2] if isinstance(report.longrepr, tuple) else str(report.longrepr)
        else:
            outcome = report.outcome
            why = str(report.longrepr.reprcrash.message) if report.failed and hasattr(report.longrepr, "reprcrash") \
                else (str(report.longrepr).strip().splitlines() or [""])[-1] if report.failed else ""
        self.counts[outcome] += 1
        why = why.removeprefix("Skipped: ")
        if outcome == "skipped" and "does not offer" in why:  # a method the backend leaves out, said once
            self.not_offered[why] = self.not_offered.get(why, 0) + 1
            return
        print(f"{outcome.upper():8s} {name}" + (f": {why}" if why else ""), flush=True)

    def pytest_sessionfinish(self, session):
        for why, n in sorted(self.not_offered.items()):
            print(f"SKIPPED  {n} check(s): {why}", flush=True)


def run(args) -> int:
    try:
        import pytest
    except ImportError:
        return error("conformance needs pytest: pip install -c constraints.txt -e '.[test]'")
    if not SUITE.is_dir():
        return error(f"--backend: the conformance suite {SUITE} is not here (an install without tests/); run it from "
                     "a checkout of isobench")
    from impls import registry

    backend = registry.resolve(args.backend)
    if isinstance(backend, registry.Unavailable):
        return error(f"--backend: {backend.reason}; `python -m bench backends` lists the registered backends")
    os.environ[EXTRA_ENV] = ",".join(dict.fromkeys([*filter(None, os.environ.get(EXTRA_ENV, "").split(",")),
                                                    args.backend]))
    if str(ROOT) not in sys.path:  # the suite imports tests.conftest from the repository root
        sys.path.insert(0, str(ROOT))
    plugin = _Outcomes(args.backend, fast=args.fast)
    print(f"conformance of {backend.id} ({args.backend}): {SUITE.relative_to(ROOT)}", flush=True)
    # this plugin prints the outcomes: pytest's own terminal output, its random order, its cache
    # and parallel workers are off (the checks of one backend run in this process, in file order);
    # so is dash's plugin, which imports dash and IPython for nothing (pyproject.toml's addopts)
    argv = [str(SUITE), "-p", "no:terminal", "-p", "no:randomly", "-p", "no:cacheprovider", "-p", "no:xdist",
            "-p", "no:dash", "--rootdir", str(ROOT), "-o", "addopts="]
    argv += ["-k", args.select] if args.select else []
    code = pytest.main(argv, plugins=[plugin])
    c = plugin.counts
    print(f"{backend.id}: {c['passed']} passed, {c['failed']} failed, {c['skipped']} skipped, "
          f"{c['xfailed']} expected failures (Capabilities.expected_failures)", flush=True)
    if c["failed"] or code not in (0, 5):  # 5: no check collected, told below
        return error(f"{backend.id} does not conform: {c['failed']} check(s) failed (pytest exit {int(code)}); "
                     "docs/backends.md says what each protocol method must do", 1)
    if not c["passed"]:
        return error(f"{backend.id}: no check passed, so nothing was verified (does methods() offer the catalog's "
                     "methods, does --select match?)", 1)
    return 0
