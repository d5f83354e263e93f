"""Timing: warm-up and compile apart, synchronised, repeated until the median is stable.

Protocol (after pyperf / pytest-benchmark): the first call (compilation, caches, allocator
warm-up) is timed alone and reported as ``first_call_s``; then calls are repeated, each one
synchronised with the device before the clock stops, until at least ``min_repeats`` samples
and ``min_time_s`` seconds are collected (capped by ``max_repeats``).  Reported: all samples,
their median and interquartile range.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any, Callable

import numpy as np


@dataclasses.dataclass
class Timing:
    first_call_s: float
    samples_s: list[float]

    @property
    def median_s(self) -> float:
        return float(np.median(self.samples_s))

    @property
    def iqr_s(self) -> float:
        q1, q3 = np.percentile(self.samples_s, [25, 75])
        return float(q3 - q1)


@dataclasses.dataclass(frozen=True)
class TimingPolicy:
    min_repeats: int = 5
    max_repeats: int = 200
    min_time_s: float = 0.2


def measure(run: Callable[[], Any], sync: Callable[[Any], None], policy: TimingPolicy = TimingPolicy()) -> tuple[Timing, Any]:
    """Time ``run`` (then ``sync(out)``); returns the timing and the first call's output."""
    clock = time.perf_counter
    t0 = clock()
    out = run()
    sync(out)
    first = clock() - t0
    samples: list[float] = []
    total = 0.0
    while len(samples) < policy.max_repeats and (len(samples) < policy.min_repeats or total < policy.min_time_s):
        t0 = clock()
        o = run()
        sync(o)
        dt = clock() - t0
        samples.append(dt)
        total += dt
    return Timing(first_call_s=first, samples_s=samples), out
