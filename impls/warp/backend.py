"""Warp backend: Warp's mesh ray query, and isobench's root finders with φ as a Warp kernel.

A plug-in, registered as a third party would register one (``pyproject.toml``:
``[project.entry-points."isobench.backends"] warp = "impls.warp.backend:WarpBackend"``, installed
by the extra ``engines``); ids ``warp:cpu`` (the default) and ``warp:cuda`` (where Warp finds a
CUDA device).  Without warp-lang, loading it raises an ImportError whose message is the install
command, which the registry reports as the reason the backend is unavailable.

What it offers:

* ``raycast`` on mesh scenes (:class:`reference.mesh.MeshSDF`): ``wp.mesh_query_ray`` over the
  mesh's BVH, float32 as Warp computes it (:mod:`impls.warp.mesh`); run at dtype float32 only
  (float64 is declined: Warp's meshes hold float32 points).  Its CONVERGED and MISS are the
  engine's answers, not a certified bracket (README "Conventions").
* The root methods ``sphere_trace``, ``hybrid_secant``, ``march_bisect``, ``march_secant`` and
  ``march_newton``, float64, on the scene trees the numba backend compiles (analytic primitives,
  CSG, transforms; :mod:`impls.warp.fields`) and on grid SDFs (:mod:`impls.warp.grid`): the core
  array algorithm of
  :mod:`impls.core.rootfind` run by numpy's compacting driver, each φ evaluation one Warp kernel
  launch over the points — the same algorithms, knobs, statuses (certified ones included) and
  counts as the numpy backend (φ bit for bit numba's, compiled without fused multiply-adds, and so
  numpy's except where numpy sums a transform's product in BLAS).
  dφ/dt for ``march_newton`` is numpy's central difference (3 evaluations).
* Declined, with the reason: meshes, neural SDFs, MLPs and user fields for the root methods (no
  Warp kernel), every non-mesh scene for ``raycast``, θ (no parameters), float32 root finding.
"""

from __future__ import annotations

import time

try:
    import warp as wp
except ImportError as exc:  # the registry turns this into Unavailable(reason=…)
    raise ImportError("warp-lang is not installed: pip install -c constraints.txt -e '.[engines]'") from exc

wp.config.log_level = wp.LOG_WARNING  # before Warp initialises: no banner or per-module load lines in a run

import numpy as np

from ..base import HostArrayBackend
from ..core.driver import CompactingSettings
from ..core.table import METHOD_TABLE
from ..engine import from_the_start
from ..protocol import Capabilities, Declined

#: root methods run with φ as a Warp kernel, and the engine's ray query
ROOT_OFFERED = ("sphere_trace", "hybrid_secant", "march_bisect", "march_secant", "march_newton")
OFFERED = ROOT_OFFERED + ("raycast",)


def _cuda_present() -> bool:
    try:
        return wp.get_cuda_device_count() > 0
    except Exception:  # a broken driver: no CUDA device to offer
        return False


def _mesh_type():
    from reference.mesh import MeshSDF

    return MeshSDF


class WarpBackend(HostArrayBackend):
    """Warp on ``device`` ("cpu" or "cuda"); arrays in and out are numpy's (``xp`` = numpy)."""

    lib = "warp"
    xp = np
    capabilities = Capabilities(
        dtypes=("float64", "float32"),
        devices=("cpu", "cuda") if _cuda_present() else ("cpu",),
        autodiff=None,
        jit=True,
        notes=("raycast: wp.mesh_query_ray over the mesh's BVH, float32 (Warp meshes hold float32 points), mesh "
               "scenes only; CONVERGED/MISS are the engine's answers, not certified; iterations and evals 0",
               "root methods (sphere_trace, hybrid_secant, march_bisect/secant/newton): float64, the core array "
               "algorithm with numpy's compacting driver, φ one Warp kernel launch per evaluation (the scene "
               "tree written as Warp source per structure; grid SDFs a trilinear kernel); same statuses and counts "
               "as numpy's",
               "declines: non-mesh scenes for raycast; meshes, neural SDFs, MLPs and user fields for the root "
               "methods; float32 root finding; θ (Warp has no autodiff wired here: no gradient or dt/dθ methods)",
               "warp:cuda: every launch's result is copied back with Array.numpy(), which waits for the kernel"),
    )
    settings = CompactingSettings()
    stop_gradient = None
    _impl = {m: METHOD_TABLE[m] for m in OFFERED}

    def __init__(self, device: str = "cpu", settings: CompactingSettings | None = None):
        super().__init__(device, settings)
        wp.init()
        self._meshes: dict = {}
        self._scenes: dict = {}
        self._built = False

    def methods(self):
        """The methods offered here (``_impl``), ``raycast`` included: the catalog leaves it to the
        engines (``MethodSpec.libs = ()``), which name it themselves."""
        return tuple(sorted(self._impl))

    def synchronize(self, out=None):
        wp.synchronize_device(self.device)

    def versions(self):
        return {"warp-lang": wp.config.version, "numpy": np.__version__}

    def declines(self, method: str, scene) -> str | None:
        """Why this backend declines ``method`` on ``scene`` although it offers the method, or None."""
        if method == "raycast":
            if not isinstance(scene, _mesh_type()):
                return (f"warp's ray query (wp.mesh_query_ray) takes triangle meshes; {type(scene).__name__} is "
                        "not one (Warp has no SDF-grid or analytic-field intersector)")
            return None
        if method in ROOT_OFFERED:
            from .fields import decline_reason

            return decline_reason(scene)
        return None

    def prepare(self, method, scene, origins, directions, *, dtype="float64", **kw):
        """:meth:`impls.base.ArrayBackend.prepare` after :meth:`declines` and the dtype each
        method runs at (raycast float32, root methods float64): :class:`impls.protocol.Declined`
        otherwise; builds the BVH or compiles φ on the first ray (``Prepared.compile_s``)."""
        if isinstance(method, str) and method in self._impl:
            reason = self.declines(method, scene)
            if reason:
                raise Declined(reason)
            if method == "raycast" and dtype != "float32":
                raise ValueError(f"raycast: dtype={dtype!r}; warp's mesh ray query computes in float32 (wp.Mesh holds "
                                 "vec3f points): use dtype='float32'")
            if method in ROOT_OFFERED and dtype == "float32":
                raise Declined("warp runs the root finders in float64 only (the scene kernels are written in float64)")
            if method == "raycast":  # the rays' start o + t_min·d in float64, before the float32 query
                return from_the_start(super().prepare, method, scene, origins, directions, dtype=dtype, **kw)
        return super().prepare(method, scene, origins, directions, dtype=dtype, **kw)

    def compile(self, fn, o, d, th):
        """Build the mesh's BVH or compile the scene's kernel by running ``fn`` on the first ray;
        ``last_compile_cache``: "compiled" when this call built them, "reused" when this backend
        had them for this scene object."""
        self._built = False
        t0 = time.perf_counter()
        fn(o[:1], d[:1], None)
        took = time.perf_counter() - t0
        self.last_compile_cache = "compiled" if self._built else "reused"
        return fn, took

    def _cached(self, table: dict, obj, build):
        """``build(obj, device)``, once per object (keyed by identity, the object kept with it so
        that a recycled id is not taken for it); marks a build for ``last_compile_cache``."""
        got = table.get(id(obj))
        if got is None or got[0] is not obj:
            got = table[id(obj)] = (obj, build(obj, self.device))
            self._built = True
        return got[1]

    def _scene(self, scene):
        from .fields import warp_scene

        return self._cached(self._scenes, scene, warp_scene)

    def _mesh(self, mesh):
        from .mesh import WarpMesh

        return self._cached(self._meshes, mesh, WarpMesh)

    def ray_eval(self, scene, theta=None):
        """``ev(o, d, t, deriv) -> (φ, dφ/dt or None, cost)`` with φ the scene's Warp kernel; x and
        the central difference exactly as :func:`impls.numpy.derivatives.ray_eval` computes them."""
        if theta is not None:
            raise Declined("warp evaluates scenes at their stored parameters only (no θ)")
        ws = self._scene(scene)

        def ev(o, d, t, deriv):
            x = o + t[:, None] * d
            if not deriv:
                return ws.phi_points(x), None, 1
            eps = np.finfo(o.dtype).eps
            h = np.cbrt(eps) * np.maximum(1.0, np.abs(t))
            h = ((t + h) - t).astype(o.dtype)
            h = np.where(h > 0, h, np.cbrt(eps))
            pts = np.concatenate([x, x + h[:, None] * d, x - h[:, None] * d])
            f3 = ws.phi_points(pts).reshape(3, -1)
            return f3[0], (f3[1] - f3[2]) / (2 * h), 3

        return ev

    def run_loop(self, alg, o, d, ev):
        from ..numpy.driver import run_loop as run_compacted_numpy

        return run_compacted_numpy(alg, o, d, ev, self.settings)

    def solve(self, method, scene, o, d, *, t_min, t_max, theta=None, **knobs):
        """``raycast``: the mesh query; a root method: the catalog's algorithm for ``knobs`` run by
        numpy's compacting driver with φ from Warp (:meth:`impls.base.ArrayBackend.solve`)."""
        if theta is not None:
            raise Declined("warp evaluates scenes at their stored parameters only (no θ)")
        if method == "raycast":
            return self._mesh(scene).first_hit(o, d, t_min, t_max)
        return super().solve(method, scene, o, d, t_min=t_min, t_max=t_max, **knobs)
