"""Every scene node evaluates the same φ with numpy, array_api_compat.torch and jax.numpy,
eagerly and under jax.jit, and θ can be a torch tensor that requires grad."""

from __future__ import annotations

import numpy as np
import pytest

from reference.cases import get_case

from reference.testing import every_node

SCENES = every_node()
EPS = np.finfo(np.float64).eps


def _points(n=300, seed=0):
    return np.random.default_rng(seed).uniform(-1.5, 1.5, size=(n, 3))


def _max_ulps(a, b, scale):
    return float(np.max(np.abs(np.asarray(a) - np.asarray(b))) / (EPS * scale))


@pytest.mark.parametrize("name", sorted(SCENES))
def test_torch_matches_numpy(name):
    torch = pytest.importorskip("torch")
    from array_api_compat import torch as xpt

    scene = SCENES[name]
    x = _points()
    ref = scene.value(x)
    out = scene.value(torch.from_numpy(x), xpt).numpy()
    # summation order may differ in the last bit (3-term sums); everything else is the same
    # IEEE operation sequence: allow 4 ulp of the value's scale
    assert _max_ulps(out, ref, 1 + np.max(np.abs(ref))) <= 4, name


@pytest.mark.parametrize("name", sorted(SCENES))
def test_jax_matches_numpy_eager_and_jit(name):
    jax = pytest.importorskip("jax")
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    scene = SCENES[name]
    x = _points()
    ref = scene.value(x)
    scale = 1 + np.max(np.abs(ref))
    eager = np.asarray(scene.value(jnp.asarray(x), jnp))
    jitted = np.asarray(jax.jit(lambda p: scene.value(p, jnp))(jnp.asarray(x)))
    assert eager.dtype == np.float64
    assert _max_ulps(eager, ref, scale) <= 4, name
    assert _max_ulps(jitted, ref, scale) <= 4, name


@pytest.mark.parametrize("name", sorted(SCENES))
def test_theta_as_torch_tensor_carries_gradients(name):
    """φ(x; θ) with θ a leaf tensor: the value equals the stored-parameter value and
    ∂φ/∂θ at surface points equals the closed-form partials of the jet."""
    torch = pytest.importorskip("torch")
    from array_api_compat import torch as xpt

    scene = SCENES[name]
    x = _points(50, seed=1)
    theta = torch.tensor(scene.param_vector(), requires_grad=True)
    phi = scene.value(torch.from_numpy(x), xpt, theta)
    np.testing.assert_allclose(phi.detach().numpy(), scene.value(x), rtol=0, atol=8 * EPS * (1 + np.abs(scene.value(x)).max()))
    if theta.numel() == 0:
        return
    jac = np.stack([torch.autograd.grad(phi[i], theta, retain_graph=True)[0].numpy() for i in range(x.shape[0])])
    _, _, dtheta = scene.jet(x)
    np.testing.assert_allclose(jac, dtheta, rtol=1e-12, atol=1e-12)


def test_jax_grad_wrt_theta_under_jit():
    jax = pytest.importorskip("jax")
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    scene = get_case("csg.union.camera.32x32").scene
    x = _points(20, seed=2)
    jac = jax.jit(jax.jacfwd(lambda th: scene.value(jnp.asarray(x), jnp, th)))(jnp.asarray(scene.param_vector()))
    np.testing.assert_allclose(np.asarray(jac), scene.jet(x)[2], rtol=1e-12, atol=1e-12)


def test_wrong_theta_length_is_named():
    scene = SCENES["torus"]
    with pytest.raises(ValueError, match="theta"):
        scene.value(_points(3), np, np.zeros(1))
