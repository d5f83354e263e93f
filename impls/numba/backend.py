"""numba backend: isobench's root finders compiled per scene, run ray by ray on the CPU.

A plug-in, registered as a third party would register one (``pyproject.toml``:
``[project.entry-points."isobench.backends"] numba = "impls.numba.backend:NumbaBackend"``,
installed by the extra ``numba``).  Without numba installed, loading it raises an ImportError
whose message is the install command, which the registry reports as the reason the backend is
unavailable.

What it offers: the root methods (``sphere_trace``, ``hybrid_secant``, ``march_bisect``,
``march_secant``, ``march_newton``) and ``render_surface`` (ρ at the hybrid's hit, shaded with
numpy), float64, on scenes it compiles (:mod:`impls.numba.fields`); a scene with a node it does
not compile is *declined* (:meth:`NumbaBackend.declines`; :class:`impls.protocol.Declined` from
``prepare``), which a run records as a skipped configuration with the reason.
"""

from __future__ import annotations

import time

try:
    import numba
except ImportError as exc:  # the registry turns this into Unavailable(reason=…)
    raise ImportError("numba is not installed: pip install -c constraints.txt -e '.[numba]'") from exc

import warnings

import numpy as np

from ..base import HostArrayBackend
from ..core.methods_root import step_field
from ..core.rootfind import void_if_refuted
from ..core.table import METHOD_TABLE
from ..methods import get_method
from ..protocol import Capabilities, Declined
from . import driver, fields

# numba tries its TBB threading layer first and, where the installed TBB is too old, warns and falls
# back to OpenMP (or its workqueue): the kernels run the same, and the warning is noise in every run
warnings.filterwarnings("ignore", message=".*The TBB threading layer requires TBB version",
                        category=numba.core.errors.NumbaWarning)

#: the methods compiled here (root finders) and ``render_surface`` (their hit, shaded with numpy)
OFFERED = ("sphere_trace", "hybrid_secant", "march_bisect", "march_secant", "march_newton", "render_surface")


class NumbaBackend(HostArrayBackend):
    """Per-ray compiled root finders (:mod:`impls.numba.driver`) on compiled scenes
    (:mod:`impls.numba.fields`); arrays are numpy's (``xp`` = numpy, float64)."""

    lib = "numba"
    xp = np
    capabilities = Capabilities(
        dtypes=("float64",),
        devices=("cpu",),
        autodiff=None,
        jit=True,
        notes=("scenes compiled with numba per structure (the scene tree written out as scalar code; compile "
               "time reported apart, once per structure and process); the constant-step marchers run ray by ray "
               "in prange loops (two rays in turn per thread without ladder steps), or, in runs that time "
               "nothing (untimed_settings: per_ray False), as the certified methods do; the certified methods "
               "(sphere_trace, hybrid_secant, render_surface) run the core array algorithm with numpy's compacting "
               "driver, each φ evaluation one compiled parallel kernel over the rays: the same algorithms, knobs, "
               "statuses and counts as numpy's array drivers",
               "offers the root methods and render_surface only: no gradient, curvature, dt/dθ or volume methods "
               "(numba has no autodiff; dφ/dt for march_newton is numpy's central difference, 3 evaluations)",
               "float64 only; declines scenes with nodes it does not compile (meshes, grids, neural SDFs, user "
               "fields): those configurations are skipped with the reason",
               "ladder = -1 means no ladder steps (a per-ray loop has no per-step overhead to amortise)"),
    )
    settings = driver.NumbaSettings()
    stop_gradient = None  # no autodiff: render_surface shades at the root finder's hit
    _impl = {m: METHOD_TABLE[m] for m in OFFERED}

    def __init__(self, device: str = "cpu", settings: driver.NumbaSettings | None = None):
        super().__init__(device, settings)
        self.id = "numba"

    def versions(self):
        import llvmlite

        return {"numba": numba.__version__, "llvmlite": llvmlite.__version__, "numpy": np.__version__}

    def declines(self, method: str, scene) -> str | None:
        """Why this backend declines ``method`` on ``scene`` although it offers the method (a node
        it does not compile), or None."""
        return fields.decline_reason(scene)

    def prepare(self, method, scene, origins, directions, **kw):
        """:meth:`impls.base.ArrayBackend.prepare`, after :meth:`declines` (raises
        :class:`impls.protocol.Declined`) for a method offered here; compiles the scene and the
        root finder on one ray (``Prepared.compile_s``; near 0 for a structure compiled before)."""
        if isinstance(method, str) and method in self._impl:
            reason = self.declines(method, scene)
            if reason:
                raise Declined(reason)
        return super().prepare(method, scene, origins, directions, **kw)

    def untimed_settings(self) -> dict:
        """Driver settings for a run that times nothing (:func:`bench.run.environment.untimed_backend`):
        no per-ray marcher kernels (``NumbaSettings.per_ray``): the constant-step marchers run the
        core array algorithm on the φ kernel the certified methods compile anyway, so a scene
        structure compiles that kernel (and φ with dφ/dt for Newton's) instead of ``march_one``
        and the lanes kernel; the per-ray results are the same."""
        return {"per_ray": False}

    def compile(self, fn, o, d, th):
        """Compile by running ``fn`` on the first ray (numba compiles a kernel on its first call)."""
        driver.LAST_COMPILE = None
        t0 = time.perf_counter()
        fn(o[:1], d[:1], None if th is None else th[:1])
        took = time.perf_counter() - t0
        self.last_compile_cache = driver.LAST_COMPILE  # None: the method ran no compiled kernel
        return fn, took

    def solve(self, method, scene, o, d, *, t_min, t_max, theta=None, **knobs):
        """The catalog's algorithm for ``method`` and ``knobs`` (:meth:`impls.methods.MethodSpec.algorithm`,
        the driver's ladder choice for ``ladder = -1``), run by the compiled per-ray driver."""
        if theta is not None:
            raise Declined("numba evaluates scenes at their stored parameters only (no θ)")
        scene = step_field(scene)  # the same surface, CSG operands at their own bounds
        alg = get_method(method).algorithm(scene, t_min, t_max, knobs, None, ladder=self.settings.ladder)
        compiled = fields.compile_scene(scene)
        return void_if_refuted(alg, driver.run_loop(compiled.key, compiled.params, alg, o, d, self.settings))
