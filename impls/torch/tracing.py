"""Ray root finders on torch tensors (mirror of ``impls/numpy/tracing.py``)."""

from __future__ import annotations

import torch

from ..protocol import Status


def sphere_trace(backend, scene, o, d, *, t_min, t_max, t_hit, tol, max_steps):
    """Sphere tracing t ← t + |φ|/L with active-set compaction; see the numpy module for the
    contract (statuses, counts).  No autograd graph is recorded (``torch.no_grad``)."""
    xp = backend.xp
    with torch.no_grad():
        n = o.shape[0]
        dev = o.device
        inv_lip = 1.0 / scene.info.lipschitz
        t = torch.full((n,), t_min, dtype=o.dtype, device=dev)
        status = torch.full((n,), int(Status.IN_PROGRESS), dtype=torch.int32, device=dev)
        iters = torch.zeros(n, dtype=torch.int32, device=dev)
        evals = torch.ones(n, dtype=torch.int32, device=dev)
        bad = ~(torch.isfinite(o).all(dim=1) & torch.isfinite(d).all(dim=1))
        status[bad] = int(Status.BAD_INPUT)

        idx = torch.nonzero(~bad).flatten()
        f = scene.value(o[idx] + t[idx, None] * d[idx], xp)
        for _ in range(max_steps + 1):
            if idx.numel() == 0:
                break
            af = f.abs()
            done = af <= tol
            nonfinite = ~torch.isfinite(f)
            status[idx[done]] = int(Status.CONVERGED)
            status[idx[nonfinite]] = int(Status.NON_FINITE)
            t[idx[nonfinite]] = float("nan")
            live = ~(done | nonfinite)
            keep = live & (iters[idx] < max_steps)
            status[idx[live & ~keep]] = int(Status.MAX_ITER)
            idx, af = idx[keep], af[keep]
            t_new = t[idx] + af * inv_lip
            iters[idx] += 1
            out = t_new > t_max
            t[idx] = torch.where(out, torch.full_like(t_new, float("inf")), t_new)
            status[idx[out]] = int(Status.MISS)
            idx = idx[~out]
            if idx.numel():
                f = scene.value(o[idx] + t[idx, None] * d[idx], xp)
                evals[idx] += 1
        return {"t": t, "status": status, "iterations": iters, "evals": evals}
