"""jax backend: ``jax:cpu`` or ``jax:gpu``; every method is jitted, compile time reported apart.

Importing this module turns on ``jax_enable_x64`` (float64 is isobench's truth dtype); arrays
are placed on the backend's device explicitly, so the global default device does not matter.
"""

from __future__ import annotations

import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jax import lax  # noqa: E402

from ..base import ArrayBackend  # noqa: E402
from ..protocol import Capabilities  # noqa: E402
from . import derivatives, driver  # noqa: E402


def _devices() -> tuple[str, ...]:
    devs = ["cpu"]
    try:
        if jax.devices("gpu"):
            devs.append("gpu")
    except RuntimeError:
        pass
    return tuple(devs)


class JaxBackend(ArrayBackend):
    lib = "jax"
    xp = jnp
    settings = driver.MaskedSettings()
    compact = False  # masked blocks: early termination of volume rays is reported, not realised
    stop_gradient = staticmethod(lax.stop_gradient)
    fori_loop = staticmethod(lax.fori_loop)  # a long unroll does not become a long trace

    def __init__(self, device: str = "cpu", settings: driver.MaskedSettings | None = None):
        self.capabilities = Capabilities(
            dtypes=("float64", "float32"),
            devices=_devices(),
            autodiff="both",
            jit=True,
            notes=("methods run under jax.jit; fixed-shape masked loops: lax.map over chunks of rays, each "
                   "compacted level by level into smaller batches, one lax.while_loop per stage and level; the "
                   "chunks' stragglers after a capped number of steps of the last level finished together "
                   "(sizes: backend.settings, recorded with every result)",),
            expected_failures=(
                ("eval_count", "masked loops evaluate φ on every ray of a chunk each iteration (and jit traces φ "
                 "once), so counted calls ≠ per-ray evals; evals counts the evaluations a ray used"),
            ),
        )
        super().__init__(device, settings)
        self.jax_device = jax.devices(device)[0]

    def asarray(self, a, dtype):
        return jax.device_put(jnp.asarray(np.asarray(a), dtype=dtype), self.jax_device)

    def to_numpy(self, a):
        return np.asarray(a)

    def synchronize(self, out=None):
        if out is not None:
            jax.block_until_ready(out)
        else:
            (jax.device_put(0.0, self.jax_device) + 0).block_until_ready()

    def compile(self, fn, *example_args):
        t0 = time.perf_counter()
        compiled = jax.jit(fn).lower(*example_args).compile()
        return compiled, time.perf_counter() - t0

    def versions(self):
        import jaxlib

        return {"jax": jax.__version__, "jaxlib": jaxlib.__version__}

    def ray_eval(self, scene, theta=None):
        return derivatives.ray_eval(scene, theta)

    def grad_hess(self, scene, x, hess, theta=None):
        return derivatives.grad_hess(scene, x, hess, theta)

    def theta_jacobian(self, fun, theta):
        return derivatives.theta_jacobian(fun, theta)

    def run_loop(self, alg, o, d, ev):
        st = self.settings
        return driver.run_loop(alg, o, d, ev, chunk=st.chunk, ratio=st.ratio, last=st.last, tail_cap=st.tail_cap)
