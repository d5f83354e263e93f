"""Ray root finders on numpy arrays: the loop driver (active-set compaction) and φ along rays.

The algorithms themselves are in :mod:`impls.core.rootfind` (shared by every backend); this
module supplies how numpy evaluates φ and dφ/dt along rays and how the per-ray loop runs.
"""

from __future__ import annotations

import numpy as np

from ..core.driver import run_compacted
from ..core import methods_root
from ..core.methods_root import make_root_finder, root_impls


def ray_eval(backend, scene, theta=None):
    """``ev(o, d, t, deriv) -> (φ, dφ/dt, cost)`` for numpy.

    numpy has no autodiff and scenes give no analytic gradient, so dφ/dt = ⟨∇φ, d⟩ is the
    central difference (φ(t + h) − φ(t − h))/2h with h = ε^{1/3}·max(1, |t|) (error
    O(h²|φ'''|) + O(ε|φ|/h), about 1e-10 relative in float64); it costs 3 evaluations per ray.
    """

    def ev(o, d, t, deriv):
        x = o + t[:, None] * d
        if not deriv:
            return scene.value(x, np, theta), None, 1
        eps = np.finfo(o.dtype).eps
        h = np.cbrt(eps) * np.maximum(1.0, np.abs(t))
        h = ((t + h) - t).astype(o.dtype)  # exactly representable step
        h = np.where(h > 0, h, np.cbrt(eps))
        f3 = scene.value(np.stack([x, x + h[:, None] * d, x - h[:, None] * d]), np, theta)
        return f3[0], (f3[1] - f3[2]) / (2 * h), 3

    return ev


BLOCK = 1 << 16  # rays per block: state in cache, loop overhead small (bench/speed.py)
POOL = 4096  # a block's last rays in a stage join the straggler pool (1/16 of a block: bench/speed.py)


def soa(a):
    """Contiguous (3, n) copy of an (n, 3) array (see :mod:`impls.core.driver`)."""
    return np.array(a.T, order="C")  # a copy even when a.T is contiguous: the driver writes to it


def _quiet():
    # finished rays are dropped before they step again, but a stage may still evaluate φ at
    # inf/NaN (MISS, NON_FINITE) on its way out: harmless, and silenced
    return np.errstate(invalid="ignore", over="ignore", divide="ignore")


def run_loop(alg, o, d, ev, block=BLOCK, pool=POOL, workers=None):
    """Run ``alg`` to completion with active-set compaction (:func:`impls.core.driver.run_compacted`)
    on ``workers`` threads (default: :func:`impls.core.driver.worker_threads`)."""
    return run_compacted(alg, np, o, d, ev, soa=soa, block=block, pool=pool, guard=_quiet, workers=workers)


# Ladder steps (impls.core.rootfind.MarchRefine.step_ladder) where the knob leaves the choice to
# the driver: 16 samples.  Once few rays are left a compacting loop step costs its per-call
# overhead whatever their number: torus ∪ box, 2^20 rays, the longest ray 1917 → 180 iterations
# (see impls/jax/tracing.py for the masked driver's choice).
LADDER = methods_root.LADDER


def solve(method, backend, scene, o, d, *, t_min, t_max, theta=None, **knobs):
    alg = make_root_finder(method, scene, t_min, t_max, knobs, theta, ladder=LADDER)
    return run_loop(alg, o, d, ray_eval(backend, scene, theta))  # the outputs of rootfind.STATE_OUT


IMPLS = root_impls(solve, "numpy")
sphere_trace = IMPLS["sphere_trace"]
