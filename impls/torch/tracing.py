"""Ray root finders on torch tensors (mirror of ``impls/numpy/tracing.py``).

Loop driver with active-set compaction (:mod:`impls.core.driver`; one host sync per iteration
to test for termination) and φ along rays; dφ/dt = ⟨∇φ, d⟩ by forward-mode autodiff
(``torch.func.jvp``), counted as one evaluation.  No autograd graph is recorded.
"""

from __future__ import annotations

import torch

from ..core.driver import run_compacted
from ..core import methods_root
from ..core.methods_root import make_root_finder, root_impls


def ray_eval(backend, scene, theta=None):
    xp = backend.xp

    def ev(o, d, t, deriv):
        if not deriv:
            return scene.value(o + t[:, None] * d, xp, theta), None, 1
        f, df = torch.func.jvp(lambda tt: scene.value(o + tt[:, None] * d, xp, theta), (t,), (torch.ones_like(t),))
        return f, df, 1

    return ev


BLOCK = 1 << 16  # see impls/numpy/tracing.py
POOL = 4096  # see impls/numpy/tracing.py


def soa(a):
    """Contiguous (3, n) copy of an (n, 3) tensor (see :mod:`impls.core.driver`)."""
    return a.T.clone(memory_format=torch.contiguous_format)  # a copy even when contiguous: the driver writes to it


def run_loop(backend, alg, o, d, ev, block=BLOCK, pool=POOL, workers=None):
    """Run ``alg`` to completion with active-set compaction (:func:`impls.core.driver.run_compacted`)
    on ``workers`` threads (default: :func:`impls.core.driver.worker_threads`); each stage's
    termination test is one host sync per iteration.  No autograd graph (``no_grad`` is per
    thread, so every thread enters it)."""
    return run_compacted(alg, backend.xp, o, d, ev, soa=soa, block=block, pool=pool, guard=torch.no_grad,
                         workers=workers, take=_take, move=_move)


def _take(a, idx, axis):
    return torch.index_select(a, axis, idx)


def _move(v, holes, src):
    v.index_copy_(0, holes, torch.index_select(v, 0, src))


LADDER = methods_root.LADDER  # see impls/numpy/tracing.py


def solve(method, backend, scene, o, d, *, t_min, t_max, theta=None, **knobs):
    alg = make_root_finder(method, scene, t_min, t_max, knobs, theta, ladder=LADDER)
    return run_loop(backend, alg, o, d, ray_eval(backend, scene, theta))


IMPLS = root_impls(solve, "torch")
sphere_trace = IMPLS["sphere_trace"]
