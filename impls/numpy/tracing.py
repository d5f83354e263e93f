"""Ray root finders on numpy arrays.

Semantics are the fixed-shape masked updates of the reference design; this backend adds
active-set compaction (φ is evaluated only on rays still iterating), which changes speed, not
results.
"""

from __future__ import annotations

import numpy as np

from ..protocol import Status


def sphere_trace(backend, scene, o, d, *, t_min, t_max, t_hit, tol, max_steps):
    """Sphere tracing (Hart 1996; lecture 'Sphere Tracing'): t ← t + |φ(o + t d)|/L.

    Starts at t_min; the step uses |φ| so a ray starting inside (φ < 0) marches to the exit.
    Converged when |φ| ≤ tol; MISS when t > t_max; MAX_ITER after ``max_steps`` steps;
    NON_FINITE if φ is NaN/inf.  ``iterations`` counts steps, ``evals`` counts φ evaluations
    (iterations + 1).  L = ``scene.info.lipschitz``.
    """
    n = o.shape[0]
    dtype = o.dtype
    inv_lip = dtype.type(1.0 / scene.info.lipschitz)
    t = np.full(n, t_min, dtype=dtype)
    status = np.full(n, Status.IN_PROGRESS, dtype=np.int32)
    iters = np.zeros(n, dtype=np.int32)
    evals = np.ones(n, dtype=np.int32)
    bad = ~(np.all(np.isfinite(o), axis=1) & np.all(np.isfinite(d), axis=1))
    status[bad] = Status.BAD_INPUT

    idx = np.flatnonzero(~bad)  # the active set
    f = scene.value(o[idx] + t[idx, None] * d[idx], np)
    for _ in range(max_steps + 1):
        if idx.size == 0:
            break
        af = np.abs(f)
        done = af <= tol
        nonfinite = ~np.isfinite(f)
        status[idx[done]] = Status.CONVERGED
        status[idx[nonfinite]] = Status.NON_FINITE
        t[idx[nonfinite]] = np.nan
        keep = ~(done | nonfinite) & (iters[idx] < max_steps)
        status[idx[~(done | nonfinite) & ~keep]] = Status.MAX_ITER
        idx, af = idx[keep], af[keep]
        t_new = t[idx] + af * inv_lip
        iters[idx] += 1
        out = t_new > t_max
        t[idx] = t_new
        status[idx[out]] = Status.MISS
        t[idx[out]] = np.inf
        idx = idx[~out]
        if idx.size:
            f = scene.value(o[idx] + t[idx, None] * d[idx], np)
            evals[idx] += 1
    return {"t": t, "status": status, "iterations": iters, "evals": evals}
