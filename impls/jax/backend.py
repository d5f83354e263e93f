"""jax backend: ``jax:cpu`` or ``jax:gpu``; every method is jitted, compile time reported apart.

Importing this module turns on ``jax_enable_x64`` (float64 is isobench's truth dtype); arrays
are placed on the backend's device explicitly, so the global default device does not matter.
"""

from __future__ import annotations

import time

import jax

jax.config.update("jax_enable_x64", True)


def _persistent_cache() -> bool:
    """Turn on jax's persistent compilation cache in ``<cache dir>/jax`` when the bench commands
    set a cache directory (:mod:`impls.cache`), for every compiled program, however small or
    quick to compile (jax's defaults keep only those that took ≥ 1 s to compile): a harness run
    compiles hundreds of kernels of a fraction of a second to a few seconds each, and pays them
    again on every run otherwise.  Returns whether it is on."""
    from ..cache import subdir

    where = subdir("jax")
    if where is None:
        return False
    jax.config.update("jax_compilation_cache_dir", str(where))
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
    return True


PERSISTENT_CACHE = _persistent_cache()
_cache_hits = [0]


def _count_hits(event: str, **kwargs) -> None:
    if event == "/jax/compilation_cache/cache_hits":
        _cache_hits[0] += 1


jax.monitoring.register_event_listener(_count_hits)

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
        """``jax.jit(fn)`` lowered and compiled for ``example_args``: (compiled, seconds).  Whether
        the executable came from the persistent cache is left in ``last_compile_cache``
        ("reused" or "compiled"; None without a cache directory)."""
        hits = _cache_hits[0]
        t0 = time.perf_counter()
        compiled = jax.jit(fn).lower(*example_args).compile()
        took = time.perf_counter() - t0
        self.last_compile_cache = None if not PERSISTENT_CACHE else ("reused" if _cache_hits[0] > hits else "compiled")
        return compiled, took

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
