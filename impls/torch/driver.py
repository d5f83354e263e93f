"""The torch loop driver: :func:`impls.core.driver.run_compacted` (active-set compaction; each
stage's termination test is one host sync per iteration) with torch's own gather and in-place
move, and no autograd graph (``no_grad`` is per thread, so every thread enters it)."""

from __future__ import annotations

import torch

from ..core.driver import CompactingSettings, run_compacted


def soa(a):
    """Contiguous (3, n) copy of an (n, 3) tensor (see :mod:`impls.core.driver`)."""
    return a.T.clone(memory_format=torch.contiguous_format)  # a copy even when contiguous: the driver writes to it


def _take(a, idx, axis):
    return torch.index_select(a, axis, idx)


def _move(v, holes, src):
    v.index_copy_(0, holes, torch.index_select(v, 0, src))


def run_loop(xp, alg, o, d, ev, settings: CompactingSettings):
    """Run ``alg`` to completion on every ray with active-set compaction, as ``settings`` say."""
    return run_compacted(alg, xp, o, d, ev, soa=soa, block=settings.block, pool=settings.pool, guard=torch.no_grad,
                         workers=settings.threads, take=_take, move=_move)
