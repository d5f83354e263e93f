"""∇φ and the Hessian in jax (``jax.grad`` of Σφ, then forward-over-reverse ``jax.jvp`` along
e_1, e_2, e_3 for the Hessian's columns), bound to :mod:`impls.core.pointwise`."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ..core import pointwise


def grad_hess(backend, scene, x, hess, theta=None):
    gfun = jax.grad(lambda y: jnp.sum(scene.value(y, jnp, theta)))
    g = gfun(x)
    if not hess:
        return g, None, 1
    cols = [jax.jvp(gfun, (x,), (jnp.zeros_like(x).at[:, i].set(1.0),))[1] for i in range(3)]
    return g, jnp.stack(cols, axis=2), 1


IMPLS = pointwise.make_impls(grad_hess)
