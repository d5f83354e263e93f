"""Ray root finders on torch tensors (mirror of ``impls/numpy/tracing.py``).

Loop driver with active-set compaction (index tensors; one host sync per iteration to test
for termination) and φ along rays; dφ/dt = ⟨∇φ, d⟩ by forward-mode autodiff
(``torch.func.jvp``), counted as one evaluation.  No autograd graph is recorded.
"""

from __future__ import annotations

import torch

from ..core import rootfind
from ..core.methods_root import make_root_finder, root_impls


def ray_eval(backend, scene, theta=None):
    xp = backend.xp

    def ev(o, d, t, deriv):
        if not deriv:
            return scene.value(o + t[:, None] * d, xp, theta), None, 1
        f, df = torch.func.jvp(lambda tt: scene.value(o + tt[:, None] * d, xp, theta), (t,), (torch.ones_like(t),))
        return f, df, 1

    return ev


def run_loop(backend, alg, o, d, ev, slack=0.0):
    """Active-set loop with lazy re-compaction; see ``impls/numpy/tracing.py:run_loop``."""
    xp = backend.xp
    with torch.no_grad():
        s = alg.init(xp, o, d, ev)
        out = {k: s[k].clone() for k in rootfind.STATE_OUT}
        idx = torch.nonzero(s["status"] == rootfind.IN).flatten()
        sub = {k: v[idx] for k, v in s.items()}
        oo, dd = o[idx], d[idx]
        live = torch.ones(idx.numel(), dtype=torch.bool, device=o.device)
        n_live = idx.numel()
        while n_live:
            sub = alg.step(xp, sub, oo, dd, ev)
            done = live & (sub["status"] != rootfind.IN)
            di = torch.nonzero(done).flatten()
            if di.numel():
                for k in rootfind.STATE_OUT:
                    out[k][idx[di]] = sub[k][di]
                live &= ~done
                n_live -= di.numel()
                if n_live < (1 - slack) * live.numel():
                    keep = torch.nonzero(live).flatten()
                    idx, oo, dd = idx[keep], oo[keep], dd[keep]
                    sub = {k: v[keep] for k, v in sub.items()}
                    live = torch.ones(keep.numel(), dtype=torch.bool, device=o.device)
    return out


def solve(method, backend, scene, o, d, *, t_min, t_max, theta=None, **knobs):
    alg = make_root_finder(method, scene, t_min, t_max, knobs)
    return run_loop(backend, alg, o, d, ray_eval(backend, scene, theta))


IMPLS = root_impls(solve, "torch")
sphere_trace = IMPLS["sphere_trace"]
