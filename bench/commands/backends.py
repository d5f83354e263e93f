"""``python -m bench backends``: every backend a run uses by default (the built-ins and the
installed entry points of the group ``isobench.backends``), one line each, named by its ``id``.

A plug-in is user code: a backend whose ``methods()`` or ``capabilities`` raise (or give back
something that is not names) gets a line naming it and the error, and the listing goes on, so that
one broken plug-in hides none of the backends after it.  Exit status: 0, or 1 when a backend's
line is such an error (``bench run`` would fail its configurations); a backend that is
unavailable here (its library not installed, a plug-in that does not load) is listed with the
reason and is not an error, as it is a skipped, not a failed, row in a run.
"""

from __future__ import annotations

import argparse


ORDER = 7
HELP = ("list backends and what they can do (exit 1 when one's methods or capabilities cannot be read)")


def add_arguments(p: argparse.ArgumentParser) -> None:
    pass


def describe(backend) -> str:
    """One backend's line after its name: methods, dtypes, autodiff and jit, read through the
    runner's contract checks (:mod:`bench.run.contract`); a :class:`bench.run.contract.BackendFault`
    (a member that raised or gave back the wrong type) passes to the caller."""
    from ..run.contract import backend_call, backend_dtypes, backend_methods

    methods = backend_methods(backend)
    dtypes = backend_dtypes(backend)
    caps = backend_call(backend, "backend.capabilities", lambda: backend.capabilities)
    autodiff = backend_call(backend, "backend.capabilities.autodiff", lambda: caps.autodiff)
    jit = backend_call(backend, "backend.capabilities.jit", lambda: caps.jit)
    return f"methods={','.join(methods)} dtypes={','.join(dtypes)} autodiff={autodiff} jit={jit}"


def run(args) -> int:
    from impls import registry

    from ..run.contract import BackendFault
    from ._common import error

    broken = []
    for spec in registry.default_ids():
        b = registry.resolve(spec)
        if isinstance(b, registry.Unavailable):
            print(f"{spec:12s} unavailable: {b.reason}", flush=True)
            continue
        # named as runs name it (bench.commands._common.resolve_backends): by its id, and by what
        # it was found by where that differs (an entry point's name)
        name = b.id + (f" (from {spec})" if spec != b.id else "")
        try:
            line = describe(b)
        except BackendFault as exc:
            broken.append(name)
            line = f"ERROR: {exc}"
        print(f"{name:12s} {line}", flush=True)
    if broken:
        return error(f"{len(broken)} backend(s) cannot say what they run: {', '.join(broken)}; a run fails their "
                     "configurations (fix the plug-in, or uninstall its entry point)", code=1)
    return 0
