"""Timing: warm-up and compile apart, synchronised, calibrated, repeated until the median is stable.

Protocol (after pyperf and pytest-benchmark):

1. The first call (compilation, caches, allocator warm-up) is timed alone: ``first_call_s``.
   Backends that compile ahead of time report ``compile_s`` separately (``Prepared.compile_s``).
2. ``warmup`` further untimed calls, for a backend that compiles (one that does not is warm after
   its first call: :func:`bench.run.configuration.warmup_policy`), unless the first call took at
   least ``warm_after_s`` (for a kernel whose compile was reported apart; ∞ otherwise): then it
   was its own warm-up, and the next call is the first sample.  With no warm-up, a first call
   of at least ``min_time_s / min_repeats`` seconds is also the first sample (calibration gives
   one call per sample there, and the repeat count, not the time, bounds the samples: a fourth
   call would be a quarter of the configuration's time).  Measured on a quick run's numpy and
   torch rows of ≥ 20 ms: first call / median of the others 1.00 (median), 1.15 (90th
   percentile); a slow first call shows as spread (the interquartile range), the median of ≥ 3
   samples stays that of the warm ones.
3. Calibration: the number of calls per sample, ``loops``, is the smallest power of two whose
   total time reaches ``min_sample_s``, so a sample of a microsecond kernel is not timer
   resolution noise (pyperf's ``--min-time`` calibration).  A sample is total time / loops.
4. Samples are repeated until at least ``min_repeats`` samples *and* ``min_time_s`` seconds,
   capped by ``max_repeats`` and by ``max_time_s``.  Every call is followed by the backend's
   ``sync(out)`` before the clock stops (device work is finished, not merely queued).

Reported: every sample, their median and interquartile range, ``loops``.
A hard limit on the whole configuration (:func:`time_limit`) turns a hang into a ``timeout`` row,
in the main thread (a signal) and in any other thread (a watchdog: a dask worker runs its
configurations in a thread, :mod:`bench.run.cluster`).
"""

from __future__ import annotations

import contextlib
import ctypes
import dataclasses
import math
import signal
import threading
import time
from typing import Any, Callable

import numpy as np


@dataclasses.dataclass
class Timing:
    """``unit_s``: the median of :data:`UNIT_CALLS` calls of the unit right before the samples and
    as many right after them (:func:`measure`), None where no unit was given."""

    first_call_s: float
    samples_s: list[float]
    loops: int = 1
    unit_s: float | None = None
    #: the output of the last timed call after the first (None where the first call was the only
    #: one): the runner checks that it is the first call's answer (the one whose accuracy is measured)
    last_out: Any = dataclasses.field(default=None, repr=False, compare=False)

    @property
    def median_s(self) -> float:
        return float(np.median(self.samples_s))

    @property
    def iqr_s(self) -> float:
        q1, q3 = np.percentile(self.samples_s, [25, 75])
        return float(q3 - q1)


@dataclasses.dataclass(frozen=True)
class TimingPolicy:
    """``min_repeats``/``min_time_s``: samples at least; ``max_repeats``/``max_time_s``: at most;
    ``min_sample_s``: calibration target of one sample; ``warmup``: untimed calls after the
    first, unless the first took at least ``warm_after_s`` (∞: never; the one-time costs a
    warm-up call absorbs, numba's dispatch, Warp's module load, XLA's first-run allocations, are
    paid in the first call; a call that long is a warm-up of its own, and the next call, the
    first sample, is warm: docs/performance.md, "How a time is measured"); ``timeout_s``: hard
    limit per configuration (0: none); ``accuracy_only``: one call, no timing samples
    (deterministic baselines)."""

    min_repeats: int = 5
    max_repeats: int = 200
    min_time_s: float = 0.2
    max_time_s: float = 10.0
    min_sample_s: float = 1e-3
    warmup: int = 1
    warm_after_s: float = 0.05
    timeout_s: float = 120.0
    accuracy_only: bool = False

    def __post_init__(self):
        for name in ("min_repeats", "max_repeats", "warmup"):
            if getattr(self, name) < (0 if name == "warmup" else 1):
                raise ValueError(f"TimingPolicy.{name}={getattr(self, name)} must be ≥ {0 if name == 'warmup' else 1}")
        for name in ("min_time_s", "max_time_s", "min_sample_s", "timeout_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"TimingPolicy.{name}={v} must be a finite number ≥ 0")
        if not self.warm_after_s >= 0:  # NaN fails too; ∞: a first call never stands in for the warm-up
            raise ValueError(f"TimingPolicy.warm_after_s={self.warm_after_s} must be a number ≥ 0 (inf: never)")


def call_times(fn: Callable[[], Any], k: int) -> list[float]:
    """Wall times in seconds of ``k`` calls of ``fn`` (perf_counter; no synchronisation: for
    host-side work such as the closed-form unit)."""
    ts = []
    for _ in range(k):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return ts


def median_time(fn: Callable[[], Any], k: int) -> float:
    """Median of :func:`call_times`."""
    return float(np.median(call_times(fn, k)))


def times_against_unit(call: Callable[[], Any], unit_fn: Callable[[], Any], repeats: int):
    """``repeats`` timed calls of ``call``, each right after the unit's median time (3 calls of
    ``unit_fn``) so that every ratio compares the two under the same machine state.  Returns
    ``(times, units, ratios, out)`` in seconds, ``out`` the last call's value (``call`` must
    synchronise its device before returning)."""
    times, units, ratios, out = [], [], [], None
    for _ in range(repeats):
        unit = median_time(unit_fn, 3)
        t0 = time.perf_counter()
        out = call()
        dt = time.perf_counter() - t0
        times.append(dt)
        units.append(unit)
        ratios.append(dt / unit)
    return times, units, ratios, out


def _timed(run: Callable[[], Any], sync: Callable[[Any], None], loops: int) -> tuple[float, Any]:
    clock = time.perf_counter
    t0 = clock()
    for _ in range(loops):
        out = run()
        sync(out)
    return clock() - t0, out


#: calls of the unit right before a configuration's samples, and as many right after them
UNIT_CALLS = 3


def measure(run: Callable[[], Any], sync: Callable[[Any], None], policy: TimingPolicy = TimingPolicy(),
            unit: Callable[[], Any] | None = None) -> tuple[Timing, Any]:
    """Time ``run`` (each call followed by ``sync(out)``); returns the timing and the first call's
    output (the one whose accuracy is measured); ``Timing.last_out`` is the last timed call's, for
    the caller to check that the calls timed computed that answer too.

    ``unit`` (host work, not synchronised: the closed-form unit of
    :func:`bench.run.configuration.closed_form_time`) is called :data:`UNIT_CALLS` times right
    before the samples and as many right after, and ``Timing.unit_s`` is the median of those
    calls: a unit measured under the same machine state as the samples, whatever the load does
    before or after them (one measured once per case took that moment's load into every ratio of
    the case: docs/performance.md, "How a time is measured")."""
    first, out = _timed(run, sync, 1)
    if policy.accuracy_only:
        return Timing(first_call_s=first, samples_s=[first], loops=1), out
    before = call_times(unit, UNIT_CALLS) if unit is not None else []
    loops = 1
    last = None
    if not policy.warmup and first >= max(policy.min_sample_s, policy.min_time_s / policy.min_repeats):
        samples, total = [first], first  # a long first call of a backend warm after it: the first sample
    else:
        for _ in range(policy.warmup if first < policy.warm_after_s else 0):
            _timed(run, sync, 1)
        while True:  # calibration: double until one sample reaches min_sample_s
            dt, last = _timed(run, sync, loops)
            if dt >= policy.min_sample_s or loops >= 2 ** 20:
                break
            loops *= 2
        samples = [dt / loops]
        total = dt
    while len(samples) < policy.max_repeats and total < policy.max_time_s and (
            len(samples) < policy.min_repeats or total < policy.min_time_s):
        dt, last = _timed(run, sync, loops)
        samples.append(dt / loops)
        total += dt
    unit_s = float(np.median(before + call_times(unit, UNIT_CALLS))) if unit is not None else None
    return Timing(first_call_s=first, samples_s=samples, loops=loops, unit_s=unit_s, last_out=last), out


class Timeout(BaseException):
    """A configuration ran past its time limit.

    A ``BaseException`` (like ``KeyboardInterrupt``), so that a user backend's ``except
    Exception`` cannot swallow it; whoever sets a limit catches it by name."""


_limits: list[tuple[float, str]] = []  # (monotonic deadline, message) of the active limits, outermost first


def _arm() -> None:
    """Set the interval timer to the nearest active deadline (re-firing every second after it, so
    a limit whose exception was swallowed by user code fires again)."""
    if not _limits:
        signal.setitimer(signal.ITIMER_REAL, 0)
        return
    left = min(d for d, _ in _limits) - time.monotonic()
    signal.setitimer(signal.ITIMER_REAL, max(left, 1e-4), 1.0)


def _on_alarm(signum, frame):
    if _limits:
        deadline, message = min(_limits)
        if time.monotonic() >= deadline - 1e-3:
            raise Timeout(message)
        _arm()  # woken early (e.g. a limit left in between): wait for the nearest deadline


@contextlib.contextmanager
def time_limit(seconds: float | None, what: str = "--timeout"):
    """Raise :class:`Timeout` in the main thread once ``seconds`` have passed (0 or None, or off
    the main thread: no limit).  ``what`` names the limit in the message (``--timeout``, the
    run's ``--budget``).

    POSIX ``SIGALRM`` (``setitimer``): the handler raises between two bytecodes of the main
    thread, so Python code, ``time.sleep`` and lock or ``join`` waits are interrupted at once; a
    long call inside a compiled kernel is interrupted when it returns to Python.  The timer keeps
    firing every second past the deadline, so user code that catches the exception and goes on
    is interrupted again.  Limits nest: the timer is set to the nearest deadline, and the
    exception raised is that of the limit that passed (an outer one may pass inside an inner
    block; it is raised again on leaving the inner block if the inner block swallowed it).

    Off the main thread (a dask worker's task thread), a watchdog thread raises the exception in
    the limited thread instead (:func:`_thread_limit`): the same between-bytecodes semantics and
    the same re-firing, except that a ``time.sleep`` or a blocking wait is not cut short (it
    raises when it returns)."""
    if not seconds:
        yield
        return
    if threading.current_thread() is not threading.main_thread() or not hasattr(signal, "setitimer"):
        with _thread_limit(seconds, what):
            yield
        return
    entry = (time.monotonic() + seconds, f"ran past the time limit of {seconds:g} s ({what})")
    outermost = not _limits
    old = signal.signal(signal.SIGALRM, _on_alarm) if outermost else None
    _limits.append(entry)
    _arm()
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        _limits.remove(entry)
        if outermost:
            signal.signal(signal.SIGALRM, signal.SIG_DFL if old is None else old)
        _arm()


class _AsyncTimeout(Timeout):
    """The :class:`Timeout` a watchdog raises in a limited thread (``PyThreadState_SetAsyncExc``
    raises a class, not an instance: the message is looked up in the thread that receives it,
    the earliest of its limits that has passed)."""

    def __init__(self, *args):
        if not args:
            now = time.monotonic()
            passed = sorted(e for e in getattr(_thread_limits, "stack", []) if e[0] <= now + 1e-3)
            args = (passed[0][1] if passed else "ran past its time limit",)
        super().__init__(*args)


_thread_limits = threading.local()  # .stack: (deadline, message) of this thread's active limits


def _set_async_exc(ident: int, exc) -> None:
    """Raise ``exc`` (a class) in thread ``ident`` at its next bytecode; None clears a pending one.
    CPython's ``PyThreadState_SetAsyncExc``: the one way to interrupt Python code in a thread
    other than the main one (signals are delivered to the main thread only)."""
    ctypes.pythonapi.PyThreadState_SetAsyncExc(ctypes.c_ulong(ident), ctypes.py_object(exc) if exc else None)


@contextlib.contextmanager
def _thread_limit(seconds: float, what: str):
    """:func:`time_limit` for a thread that is not the main one: a daemon watchdog thread waits
    for the deadline, then raises :class:`_AsyncTimeout` in this thread, again every second until
    the block is left.  Leaving the block stops the watchdog under a lock and clears an exception
    sent but not yet raised, so none lands after the block."""
    ident = threading.get_ident()
    entry = (time.monotonic() + seconds, f"ran past the time limit of {seconds:g} s ({what})")
    stack = _thread_limits.__dict__.setdefault("stack", [])
    stack.append(entry)
    left, lock, inside = threading.Event(), threading.Lock(), [True]

    def watch():
        if left.wait(max(entry[0] - time.monotonic(), 0.0)):
            return
        while True:
            with lock:
                if not inside[0]:
                    return
                _set_async_exc(ident, _AsyncTimeout)
            if left.wait(1.0):
                return

    watchdog = threading.Thread(target=watch, name="isobench-time-limit", daemon=True)
    try:
        watchdog.start()  # inside the try: a tiny limit may pass while the watchdog starts
        yield
    finally:
        while True:  # an exception landing during this clean-up means the block ended late: clean up again
            try:
                with lock:
                    inside[0] = False
                    _set_async_exc(ident, None)
                break
            except _AsyncTimeout:
                continue
        left.set()
        stack.remove(entry)
