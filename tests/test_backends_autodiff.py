"""torch ``gradcheck`` and jax ``check_grads`` on the differentiable paths of the backends
(IDR's forward trick and the unrolled sphere tracer, lecture eq. 16), in float64."""

from __future__ import annotations

import numpy as np
import pytest

from impls.core import param_grad
from tests.test_conformance import SPHERE, AlgebraicSphere, camera

SCENES = [SPHERE, AlgebraicSphere()]


def _rays(scene):
    o, d = camera(4)
    t = scene.first_hit(o, d, 0.0)
    hit = np.isfinite(t)
    o, d, t = o[hit], d[hit], t[hit]
    x = o + t[:, None] * d
    g = scene.normal_exact(x)  # direction of ∇φ; gd only needs to be a fixed non-zero constant
    return o, d, t, x, np.einsum("ij,ij->i", g, d)


@pytest.mark.parametrize("scene", SCENES, ids=lambda s: s.kind)
def test_torch_gradcheck(scene):
    torch = pytest.importorskip("torch")
    import array_api_compat.torch as xp

    o, d, t, x, gd = (torch.as_tensor(a, dtype=torch.float64) for a in _rays(scene))
    th = torch.as_tensor(scene.param_vector(), dtype=torch.float64).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda th: param_grad.idr_depth(xp, scene, x, t, gd, th), (th,))
    assert torch.autograd.gradcheck(lambda th: param_grad.unrolled_depth(xp, scene, o, d, 0.0, 12, th), (th,))


@pytest.mark.parametrize("scene", SCENES, ids=lambda s: s.kind)
def test_jax_check_grads(scene):
    pytest.importorskip("jax")
    import impls.jax.backend  # noqa: F401  (turns on float64)
    import jax.numpy as jnp
    from jax import lax
    from jax.test_util import check_grads

    o, d, t, x, gd = (jnp.asarray(a) for a in _rays(scene))
    th = jnp.asarray(scene.param_vector())
    check_grads(lambda th: param_grad.idr_depth(jnp, scene, x, t, gd, th), (th,), order=2, modes=("fwd", "rev"))
    check_grads(lambda th: param_grad.unrolled_depth(jnp, scene, o, d, 0.0, 12, th, lax.fori_loop), (th,), order=1,
                modes=("fwd", "rev"))
