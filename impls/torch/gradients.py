"""∇φ and the Hessian on torch by reverse-mode autodiff (double backward), bound to the shared
formulas of :mod:`impls.core.pointwise`.  Points are independent, so ∇ of Σφ(x_k) gives every
∇φ(x_k) in one backward pass, and the Hessian's rows are three more passes over ∂_iφ."""

from __future__ import annotations

import torch

from ..core import pointwise


def grad_hess(backend, scene, x, hess, theta=None):
    with torch.enable_grad():
        x = x.detach().requires_grad_(True)
        f = scene.value(x, backend.xp, theta)
        (g,) = torch.autograd.grad(f.sum(), x, create_graph=hess)
        if not hess:
            return g.detach(), None, 1
        rows = [torch.autograd.grad(g[:, i].sum(), x, retain_graph=i < 2)[0] for i in range(3)]
    return g.detach(), torch.stack(rows, dim=1).detach(), 1


IMPLS = pointwise.make_impls(grad_hess)
