"""Derivatives on torch by autodiff: dφ/dt along rays by forward mode (``torch.func.jvp``, one
evaluation), ∇φ and the Hessian at points by reverse mode (double backward), Jacobians in θ by
``torch.func.jacfwd``.  No autograd graph is recorded outside ``grad_hess``."""

from __future__ import annotations

import torch


def ray_eval(xp, scene, theta=None):
    """``ev(o, d, t, deriv) -> (φ, dφ/dt, cost)``; dφ/dt = ⟨∇φ, d⟩ by ``torch.func.jvp`` in t."""

    def ev(o, d, t, deriv):
        if not deriv:
            return scene.value(o + t[:, None] * d, xp, theta), None, 1
        f, df = torch.func.jvp(lambda tt: scene.value(o + tt[:, None] * d, xp, theta), (t,), (torch.ones_like(t),))
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
