"""Claim 11: differentiable sphere tracing x_n(θ) = x_{n−1} + d φ(x_{n−1}; θ) (eq. 16), a differentiable
secant, and "differentiable root finding" (the lecture's open question, answered here by implicit
differentiation, eq. 8, at the current iterate): their gradients against the analytic dt/dθ as the
iteration count grows.

Scene: the reference unit sphere (θ = centre, radius) evaluated through its own array-API formula with
torch float64 (autograd through the unrolled iterations).  The unrolling stays here rather than in the
backends' ``dt_unrolled``: this claim studies the derivative of *every* iterate k = 1…k_max, converged or
not, while ``dt_unrolled`` is a finished method that returns dt/dθ only where its tracer reached the
surface (|φ|/L ≤ 1e-9; otherwise MAX_ITER with the value blanked) — one call per k would also cost
O(k_max²) and still hide the transient this claim measures.  Where both define it (the k_max-th iterate on
rays whose tracer converged) they are the same quantity, and the key numbers report their difference
(torch backend, autodiff through the same t ← t + φ/L steps from t = 0).  There is no backend
counterpart of the unrolled secant.  Rays along −z at impact b; truth dt/dθ = (−b/s, 0, −1, −r/s), s = √((r−b)(r+b))
(see claim 7).  Unrolled sphere tracing differentiates t_{k+1} = t_k + φ(o + t_k d; θ), whose derivative
obeys t'_{k+1} = (1 + ⟨∇φ, d⟩) t'_k + ∂φ/∂θ: it converges to the implicit derivative geometrically with
ratio 1 − |⟨n, d⟩| (slow at grazing incidence).
"""

from __future__ import annotations


import numpy as np

from reference import Sphere

from .scenes import implicit_and_trick, sphere_dt_truth
from .figures import figure
from .ledger import LEDGER, Trial

RTOL = 1e-8


def _unrolled(kind, o, d, k_max):
    """Per-iteration (t_k, dt_k/dθ) of one ray through ``kind`` ∈ {sphere tracing, secant} (torch autograd)."""
    import array_api_compat.torch as xp
    import torch

    scene = Sphere()
    theta = torch.tensor(scene.param_vector(), dtype=torch.float64, requires_grad=True)
    ot = torch.tensor(o, dtype=torch.float64)
    dt = torch.tensor(d, dtype=torch.float64)

    def g(t):
        return scene.value((ot + t * dt)[None, :], xp, theta)[0]

    ts, grads = [], []
    if kind == "sphere tracing":
        t = torch.zeros((), dtype=torch.float64)
        for _ in range(k_max):
            t = t + g(t)
            ts.append(float(t.detach()))
            grads.append(torch.autograd.grad(t, theta, retain_graph=True)[0].numpy().copy())
    else:  # secant from t0 = 0, t1 = 0.5 (both in front of the surface)
        t0 = torch.zeros((), dtype=torch.float64)
        t1 = torch.full((), 0.5, dtype=torch.float64)
        g0, g1 = g(t0), g(t1)
        for _ in range(k_max):
            if float(g1.detach()) == float(g0.detach()):  # converged: a further step would divide 0 by 0
                ts.append(ts[-1])
                grads.append(grads[-1])
                continue
            t2 = t1 - g1 * (t1 - t0) / (g1 - g0)
            t0, g0, t1 = t1, g1, t2
            g1 = g(t1)
            ts.append(float(t1.detach()))
            grads.append(torch.autograd.grad(t1, theta, retain_graph=True)[0].numpy().copy())
    return np.array(ts), np.array(grads)


def _backend_agreement(bs, k_max, own):
    """max over rays of |own − dt_unrolled(steps=k_max)| from the torch backend on the rays where its
    tracer converged (NaN if none did, or the backend is unavailable: reported, never fatal)."""
    from . import adapters

    try:
        b = adapters.backend("torch:cpu")
    except RuntimeError:
        return float("nan")
    o = np.stack([np.array([bb, 0.0, 3.0]) for bb in bs])
    d = np.tile([0.0, 0.0, -1.0], (len(bs), 1))
    prep = b.prepare("dt_unrolled", Sphere(), o, d, t_min=0.0, t_max=10.0, steps=int(k_max))
    res = prep.result(prep.run())
    ok = res.status == 0
    return float(np.abs(res.outputs["dt_dtheta"][ok] - own[ok]).max()) if ok.any() else float("nan")


_HOW = ("unit sphere, rays at impact b ∈ {0, 0.6, 0.9, 0.99}; torch autograd through k unrolled "
    "iterations (sphere tracing from t=0; secant from 0, 0.5) and implicit differentiation (eq. 8) at the "
    f"k-th secant iterate; a trial (method × ray) holds if the relative error after k_max iterations is ≤ {RTOL:g}; "
    "fitted per-step error ratio of unrolled sphere tracing vs 1 − |⟨n,d⟩|")
_SCOPE = ("rays that hit the surface transversally, differentiated after a finite unrolling of k_max iterations "
          "(the budget a renderer spends); named class: rays for which the method's own convergence rate reaches "
          "the tolerance within that budget")


def _unrolled_all(ctx):
    """Trials of claims 11a–11c, measured once: (part → trials, key numbers, figure)."""
    k_max = 60 if ctx.quick else 200
    bs = np.array([0.0, 0.6, 0.9, 0.99])
    truth, cos = sphere_dt_truth(bs)
    trials, key, curves, st_final = [], {}, [], []
    scene = Sphere()
    for b, tr, c in zip(bs, truth, cos):
        o = np.array([b, 0.0, 3.0])
        d = np.array([0.0, 0.0, -1.0])
        for method in ("sphere tracing", "secant"):
            ts, gr = _unrolled(method, o, d, k_max)
            err = np.linalg.norm(gr - tr, axis=-1) / np.linalg.norm(tr)
            reachable = method != "sphere tracing" or (1 - c) ** k_max <= RTOL
            trials.append(("11a" if method == "sphere tracing" else "11b",
                           Trial(f"unrolled {method}, |⟨n,d⟩|={c:.3g}, {k_max} iterations", bool(err[-1] <= RTOL),
                                 {"rel_err": float(err[-1])}, classes=("within budget",) if reachable else ())))
            curves.append((f"unrolled {method}, |⟨n,d⟩|={c:.2g}", err))
            if method == "sphere tracing":
                st_final.append(gr[-1])
                ok = (err > 1e-13) & (err < 1e-1)
                if ok.sum() >= 3:
                    ratio = float(np.exp(np.polyfit(np.flatnonzero(ok), np.log(err[ok]), 1)[0]))
                    key[f"sphere tracing |⟨n,d⟩|={c:.3g}: error ratio per step (predicted {1 - c:.3g})"] = ratio
            else:
                imp, _ = implicit_and_trick(scene, np.tile(o, (ts.size, 1)), np.tile(d, (ts.size, 1)), ts)
                e_imp = np.linalg.norm(imp - tr, axis=-1) / np.linalg.norm(tr)
                trials.append(("11c", Trial(f"implicit (eq. 8) at the secant iterate, |⟨n,d⟩|={c:.3g}, {k_max} "
                                            "iterations", bool(e_imp[-1] <= RTOL), {"rel_err": float(e_imp[-1])},
                                            classes=("within budget",))))
                curves.append((f"implicit at secant iterate, |⟨n,d⟩|={c:.2g}", e_imp))
                key[f"|⟨n,d⟩|={c:.3g}: iterations to rel err ≤ {RTOL:g} (unrolled secant, implicit)"] = [
                    int(np.argmax(err <= RTOL)) + 1 if (err <= RTOL).any() else None,
                    int(np.argmax(e_imp <= RTOL)) + 1 if (e_imp <= RTOL).any() else None]
    key["max |dt/dθ (this unrolling) − backend dt_unrolled| at k_max, rays where the backend converged"] = \
        _backend_agreement(bs, k_max, np.array(st_final))
    fig, axes = figure(3, 1, 4.4, 3.8)
    for name, err in curves:
        ax = axes[0 if name.startswith("unrolled sphere") else 1 if name.startswith("unrolled secant") else 2]
        ax.semilogy(np.arange(1, err.size + 1), np.maximum(err, 1e-17), label=name.split(", ")[-1])
    for ax, title in zip(axes, ("unrolled sphere tracing (eq. 16)", "unrolled secant", "implicit at secant iterate")):
        ax.axhline(RTOL, color="k", ls=":", lw=0.8)
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("iterations k")
        ax.set_ylabel("relative error of dt/dθ (dimensionless)")
        ax.legend(fontsize=7)
    return {p: [t for q, t in trials if q == p] for p in ("11a", "11b", "11c")}, key, fig


LEDGER.parts(_unrolled_all, [
    dict(id="11a",
         statement="differentiable sphere tracing (autodiff through the unrolled eq. 16) gives the surface gradient dt/dθ",
         equation="eq. (16)",
         how_checked=_HOW,
         scope=_SCOPE + ": (1 − |⟨n,d⟩|)^k_max ≤ tolerance (sphere tracing's error ratio per step is 1 − |⟨n,d⟩|)"),
    dict(id="11b",
         statement="differentiable secant (autodiff through the unrolled secant iterations) gives dt/dθ",
         equation="slide 'Other rendering techniques' (open question)",
         how_checked=_HOW,
         scope=_SCOPE + " (every ray here: the secant converges superlinearly)"),
    dict(id="11c",
         statement="differentiable root finding (implicit differentiation, eq. 8, at the root finder's iterate) gives "
         "dt/dθ",
         equation="eq. (8) with slide 'Other rendering techniques' (open question)",
         how_checked=_HOW,
         scope=_SCOPE + " (every ray here)"),
])
