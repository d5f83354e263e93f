"""The torch loop driver: :func:`impls.core.driver.run_compacted` (active-set compaction; each
stage's termination test is one host sync per iteration) with no autograd graph (``no_grad`` is
per thread, so every thread enters it).

On the CPU the loop's own arithmetic (the root finders' steps, statuses and compaction) runs on
numpy views of the same memory (``Tensor.numpy``/``torch.from_numpy``, no copy), and only φ and
its derivatives run in torch (:func:`impls.torch.derivatives.ray_eval`, called with tensors that
share the loop's arrays).  Why: a step is ~100 elementwise operations whose arrays shrink to a
few rays as the rays finish, where each costs its per-call overhead, 3–5 µs in torch against
about 1 µs in numpy; the straggler steps of a torch run took 4–5× numpy's time on the same
evaluations (mlp.camera.32x32, sphere tracing, 512 steps: 0.55 s against 0.12 s a call).
Measured against the torch loop on five root finders × the stability plan and the quick cases
(64 runs per dtype): float64 outputs the same bit for bit; float32 the same statuses, with the
depth or evaluation count of 1–26 rays in 11 runs different at rounding level (some float32
operation rounds differently in the two libraries; which one was not traced).  On a GPU the loop
stays in torch on the device."""

from __future__ import annotations

import warnings

import torch

from ..core.driver import CompactingSettings, run_compacted
from ..numpy import driver as numpy_driver


def soa(a):
    """Contiguous (3, n) copy of an (n, 3) tensor (see :mod:`impls.core.driver`)."""
    return a.T.clone(memory_format=torch.contiguous_format)  # a copy even when contiguous: the driver writes to it


def _take(a, idx, axis):
    return torch.index_select(a, axis, idx)


def _move(v, holes, src):
    v.index_copy_(0, holes, torch.index_select(v, 0, src))


# numpy's loop hands φ read-only views (broadcast depths, rays), which torch.from_numpy wraps with a
# warning that writing through them is undefined: φ only reads its inputs
warnings.filterwarnings("ignore", message="The given NumPy array is not writable", category=UserWarning,
                        module=__name__)


def _host_ev(ev):
    """``ev`` on numpy arrays: the points and depths as tensors sharing their memory, φ and dφ/dt
    back as numpy views (no autograd graph is recorded: the loop's threads are not in no_grad)."""
    def host(o, d, t, deriv):
        with torch.no_grad():
            f, df, cost = ev(torch.from_numpy(o), torch.from_numpy(d), torch.from_numpy(t), deriv)
        return f.numpy(), (None if df is None else df.numpy()), cost

    return host


def run_loop(xp, alg, o, d, ev, settings: CompactingSettings):
    """Run ``alg`` to completion on every ray with active-set compaction, as ``settings`` say."""
    if o.device.type == "cpu":
        out = numpy_driver.run_loop(alg, o.detach().numpy(), d.detach().numpy(), _host_ev(ev), settings)
        return {k: torch.from_numpy(v) for k, v in out.items()}
    return run_compacted(alg, xp, o, d, ev, soa=soa, block=settings.block, pool=settings.pool, guard=torch.no_grad,
                         workers=settings.threads, take=_take, move=_move)
