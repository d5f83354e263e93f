"""Whether a ``KeyboardInterrupt`` is the user's Ctrl-C or a plug-in's own ``raise``.

A Ctrl-C (SIGINT, which ``bench run``'s supervisor passes on to the run) must stop the run; a
``KeyboardInterrupt`` (or another ``BaseException``) that a plug-in backend or a user's field
raises by itself is that code's failure, a failed row like any exception (the 2026-11-30 probe:
a plug-in raising ``KeyboardInterrupt`` in ``prepare`` ended the run with exit 130 and no rows,
and ``--resume`` died at the same place).  Python raises ``KeyboardInterrupt`` for SIGINT from its
default handler; :func:`watching` wraps that handler so that the signal is recorded first, and
:func:`signalled` tells the two apart.
"""

from __future__ import annotations

import contextlib
import signal
import threading

_count = 0  # SIGINTs received while watching


def _on_sigint(signum, frame):
    global _count
    _count += 1
    signal.default_int_handler(signum, frame)  # raises KeyboardInterrupt, as Python's own handler


@contextlib.contextmanager
def watching():
    """Record SIGINTs while the block runs (in the main thread, where Python's default handler is
    installed; elsewhere nothing changes, and :func:`signalled` reads the handler as it finds it)."""
    global _count
    if threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        yield
        return
    _count = 0
    signal.signal(signal.SIGINT, _on_sigint)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def signalled() -> bool:
    """Whether a KeyboardInterrupt now is a Ctrl-C: a SIGINT arrived while watched; never where
    SIGINT is ignored (a background job of a script, ``nohup``: no Ctrl-C can raise one, so it
    is code's own); under any other handler it cannot be told apart, and stopping is the safe
    reading.  Never off the main thread either: Python runs signal handlers, and raises a Ctrl-C's
    KeyboardInterrupt, in the main thread only, so one in a worker's thread (a ``--cluster``
    configuration) is code's own (it killed the dask worker four times over, a KilledWorker row)."""
    if threading.current_thread() is not threading.main_thread():
        return False
    handler = signal.getsignal(signal.SIGINT)
    if handler is _on_sigint:
        return _count > 0
    return handler != signal.SIG_IGN


def is_fault(exc: BaseException) -> bool:
    """Whether ``exc``, raised by a configuration's code, is that code's failure (a failed row)
    rather than a stop of the run: anything but a Ctrl-C's KeyboardInterrupt and the run's own
    stops (GeneratorExit; the time limit's Timeout is caught before this is asked)."""
    if isinstance(exc, KeyboardInterrupt):
        return not signalled()
    return not isinstance(exc, GeneratorExit)
