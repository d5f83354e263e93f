"""Derivatives on torch by autodiff: dφ/dt along rays and ∇φ at points by reverse mode (one
backward pass over the sum: points are independent), the Hessian by double backward, Jacobians
in θ by ``torch.func.jacfwd``.  No autograd graph is kept unless the caller records one."""

from __future__ import annotations

import torch


def ray_eval(xp, scene, theta=None):
    """``ev(o, d, t, deriv) -> (φ, dφ/dt, cost)``; dφ/dt = ⟨∇φ, d⟩ = ∂/∂t_i Σ_k φ(o_k + t_k d_k), one
    backward pass (rays are independent, as in :func:`grad_hess`).

    Reverse mode, not forward: torch's forward-mode formulas for ``maximum``, ``minimum`` and
    other ops the scenes use run through Python decompositions (``torch._refs``) on every call,
    which made ``torch.func.jvp`` (and ``torch.autograd.forward_ad``) several times slower than
    this backward pass on every scene kind (measured in the CHANGELOG; the same φ, dφ/dt to
    rounding).  Where the caller records a graph (grad enabled) φ and dφ/dt keep theirs, so they
    stay differentiable in θ."""

    def ev(o, d, t, deriv):
        if not deriv:
            return scene.value(o + t[:, None] * d, xp, theta), None, 1
        outer = torch.is_grad_enabled()
        with torch.enable_grad():
            tt = t if t.requires_grad else t.detach().requires_grad_(True)
            f = scene.value(o + tt[:, None] * d, xp, theta)
            if f.requires_grad:
                (df,) = torch.autograd.grad(f.sum(), tt, create_graph=outer, materialize_grads=True)
            else:  # φ constant along the rays (outside the graph): dφ/dt is exactly zero
                df = torch.zeros_like(t)
        if not outer:
            f, df = f.detach(), df.detach()
        return f, df, 1

    return ev


def grad_hess(xp, scene, x, hess, theta=None):
    """Points are independent, so ∇ of Σφ(x_k) gives every ∇φ(x_k) in one backward pass, and the
    Hessian's rows are three more passes over ∂_iφ.  Cost: 1 evaluation per point."""
    with torch.enable_grad():
        x = x.detach().requires_grad_(True)
        f = scene.value(x, xp, theta)
        # A field that is constant (or linear) in x leaves φ (or ∇φ) outside the graph, and
        # autograd.grad refuses such outputs: the derivative is then exactly zero.
        if f.requires_grad:
            (g,) = torch.autograd.grad(f.sum(), x, create_graph=hess, materialize_grads=True)
        else:
            g = torch.zeros_like(x)
        if not hess:
            return g.detach(), None, 1
        if not g.requires_grad:
            return g.detach(), torch.zeros(x.shape + (3,), dtype=x.dtype, device=x.device), 1
        rows = [torch.autograd.grad(g[:, i].sum(), x, retain_graph=i < 2, materialize_grads=True)[0]
                for i in range(3)]
    return g.detach(), torch.stack(rows, dim=1).detach(), 1


def theta_jacobian(fun, theta):
    """Forward-mode Jacobian in θ (P tangents, vectorised; one φ call per point)."""
    with torch.no_grad():
        return torch.func.jacfwd(fun)(theta), 1
