"""Ray root finders on numpy arrays: the loop driver (active-set compaction) and φ along rays.

The algorithms themselves are in :mod:`impls.core.rootfind` (shared by every backend); this
module supplies how numpy evaluates φ and dφ/dt along rays and how the per-ray loop runs.
"""

from __future__ import annotations

import numpy as np

from ..core import rootfind
from ..core.methods_root import ROOT_METHODS, make_root_finder


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


def run_loop(alg, o, d, ev):
    """Run ``alg`` to completion, stepping only the rays still IN_PROGRESS (compaction)."""
    # copies: init may alias one array under several names, and the scatter below is in place
    s = {k: np.array(v, copy=True) for k, v in alg.init(np, o, d, ev).items()}
    idx = np.flatnonzero(s["status"] == rootfind.IN)
    while idx.size:
        sub = {k: v[idx] for k, v in s.items()}
        new = alg.step(np, sub, o[idx], d[idx], ev)
        for k, v in new.items():
            s[k][idx] = v
        idx = idx[new["status"] == rootfind.IN]
    return s


def solve(method, backend, scene, o, d, *, t_min, t_max, theta=None, **knobs):
    alg = make_root_finder(method, scene, t_min, t_max, knobs)
    return run_loop(alg, o, d, ray_eval(backend, scene, theta))


def _root_impl(method):
    def impl(backend, scene, o, d, *, t_min, t_max, t_hit, **knobs):
        return rootfind.outputs(solve(method, backend, scene, o, d, t_min=t_min, t_max=t_max, **knobs))

    impl.__name__ = method
    impl.__doc__ = f"{method} on numpy (see impls.core.rootfind and impls.methods.METHODS[{method!r}])."
    return impl


IMPLS = {m: _root_impl(m) for m in ROOT_METHODS}
sphere_trace = IMPLS["sphere_trace"]
