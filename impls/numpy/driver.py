"""The numpy loop driver: :func:`impls.core.driver.run_compacted` (active-set compaction) with
numpy's contiguous copies and floating-point error state."""

from __future__ import annotations

import numpy as np

from ..core.driver import CompactingSettings, run_compacted


def soa(a):
    """Contiguous (3, n) copy of an (n, 3) array (see :mod:`impls.core.driver`)."""
    return np.array(a.T, order="C")  # a copy even when a.T is contiguous: the driver writes to it


def _quiet():
    # finished rays are dropped before they step again, but a stage may still evaluate φ at
    # inf/NaN (MISS, NON_FINITE) on its way out: harmless, and silenced
    return np.errstate(invalid="ignore", over="ignore", divide="ignore")


def run_loop(alg, o, d, ev, settings: CompactingSettings):
    """Run ``alg`` to completion on every ray with active-set compaction, as ``settings`` say."""
    return run_compacted(alg, np, o, d, ev, soa=soa, block=settings.block, pool=settings.pool, guard=_quiet,
                         workers=settings.threads)
