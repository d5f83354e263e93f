"""Ray root finders on numpy arrays: the loop driver (active-set compaction) and φ along rays.

The algorithms themselves are in :mod:`impls.core.rootfind` (shared by every backend); this
module supplies how numpy evaluates φ and dφ/dt along rays and how the per-ray loop runs.
"""

from __future__ import annotations

import numpy as np

from ..core import rootfind
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


def run_loop(alg, o, d, ev, slack=0.0):
    """Run ``alg`` to completion on the active set; returns the per-ray outputs.

    The state is kept compacted to the active rays (not gathered from and scattered back to
    full-size arrays each step); a ray's outputs are written out the step it finishes.  With
    ``slack`` > 0 the set is re-compacted only once more than that fraction has finished —
    less copying, but finished rays are then stepped (φ evaluated) without being counted in
    ``evals``, so the default 0 keeps ``evals`` equal to the evaluations made.
    """
    s = alg.init(np, o, d, ev)
    out = {k: np.array(s[k], copy=True) for k in rootfind.STATE_OUT}
    idx = np.flatnonzero(s["status"] == rootfind.IN)
    sub = {k: v[idx] for k, v in s.items()}
    oo, dd = o[idx], d[idx]
    live = np.ones(idx.size, dtype=bool)
    while idx.size:
        # finished-but-not-yet-dropped rays may step from t = inf/NaN: harmless, and silenced
        with np.errstate(invalid="ignore", over="ignore"):
            sub = alg.step(np, sub, oo, dd, ev)
        done = live & (sub["status"] != rootfind.IN)
        if done.any():
            for k in rootfind.STATE_OUT:
                out[k][idx[done]] = sub[k][done]
            live &= ~done
            if live.sum() < (1 - slack) * live.size:
                idx, oo, dd = idx[live], oo[live], dd[live]
                sub = {k: v[live] for k, v in sub.items()}
                live = np.ones(idx.size, dtype=bool)
    return out


def solve(method, backend, scene, o, d, *, t_min, t_max, theta=None, **knobs):
    alg = make_root_finder(method, scene, t_min, t_max, knobs)
    return run_loop(alg, o, d, ray_eval(backend, scene, theta))  # the outputs of rootfind.STATE_OUT


IMPLS = root_impls(solve, "numpy")
sphere_trace = IMPLS["sphere_trace"]
