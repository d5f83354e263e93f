"""Host side of a Warp φ kernel: one launch over a batch of points, numpy in and out (the root
finders' array algorithm evaluates φ through it once per step: :mod:`impls.warp.fields`,
:mod:`impls.warp.grid`)."""

from __future__ import annotations

import numpy as np


def launch_on_points(kernel, x: np.ndarray, inputs: list, device: str) -> np.ndarray:
    """``kernel(X, *inputs, F)`` launched over the float64 points ``x`` (n, 3); returns F (n,) as
    numpy.  On the CPU, X and F are the numpy arrays' own memory (``copy=False``: Warp references
    a contiguous CPU array) and the launch returns once the kernel has run, so a root finder's
    step, one call per step, pays no copy in or out (docs/performance.md, "Warp on the CPU").  On
    a GPU, X is copied in and F copied back (``Array.numpy`` waits for the launch's stream)."""
    import warp as wp

    n = x.shape[0]
    if n == 0:
        return np.empty(0)
    xc = np.ascontiguousarray(x, np.float64)
    if wp.get_device(device).is_cpu:
        out = np.empty(n, np.float64)
        X = wp.array(xc, dtype=wp.float64, device=device, copy=False)
        F = wp.array(out, dtype=wp.float64, device=device, copy=False)
        wp.launch(kernel, dim=n, inputs=[X, *inputs, F], device=device)
        return out
    X = wp.array(xc, dtype=wp.float64, device=device)
    F = wp.empty(n, dtype=wp.float64, device=device)
    wp.launch(kernel, dim=n, inputs=[X, *inputs, F], device=device)
    return F.numpy()
