"""Mitsuba 3 backend: the engine's first-hit ray query on grid SDFs and triangle meshes.

A plug-in, registered as a third party would register one (``pyproject.toml``:
``[project.entry-points."isobench.backends"] mitsuba = "impls.mitsuba.backend:MitsubaBackend"``,
installed by the extra ``engines``); ids ``mitsuba:llvm`` (the default: variant ``llvm_ad_rgb``,
Dr.Jit's LLVM backend on the CPU) and ``mitsuba:cuda`` (``cuda_ad_rgb``, where Dr.Jit finds a
CUDA device).  Without mitsuba and drjit, loading it raises an ImportError whose message is the
install command; without a usable libLLVM (:mod:`impls.mitsuba.llvm`, which sets
``DRJIT_LIBLLVM_PATH`` when it finds one) the LLVM device is unavailable with the reason.

What it offers: ``raycast`` — ``Scene.ray_intersect_preliminary`` on the scene's one shape
(:mod:`impls.mitsuba.scenes`: ``sdfgrid`` for a closed :class:`reference.grid.GridSDF`, a
``Mesh`` for a :class:`reference.mesh.MeshSDF`), float32 as Mitsuba computes (rays, depths and
the grid are single precision), so it runs at dtype float32 only.  CONVERGED is the engine's
hit, MISS its "no hit" (README "Conventions": an engine's answer, not a certified bracket);
``iterations`` and ``evals`` are 0; the output ``normal`` (as :mod:`impls.engine`'s) is the
geometric normal of the hit (``compute_surface_interaction``: the face's for a mesh, the
interpolant's gradient for the grid), normalised in float64, NaN on a MISS.  The search covers [t_min, t_max]: the ray starts at
o + t_min·d (float64, then rounded) with ``maxt`` = t_max − t_min, and t_min is added back.

No dt/dθ (param_grad family): isobench's grid and mesh scenes have no parameters θ (a
:class:`GridSDF` is built with ``differentiable=False``, a :class:`MeshSDF` has none), and
Mitsuba 3.9's ``sdfgrid`` exposes its ``grid`` and ``to_world`` as non-differentiable; Mitsuba's
differentiable quantity for a mesh is the rendered image's derivative w.r.t. vertex positions,
which is not a first-hit dt/dθ of a scene parameter isobench defines.

Dr.Jit evaluates lazily: a query only records a kernel.  :meth:`MitsubaBackend.solve` evaluates
the depths and hit mask (``dr.eval``) and waits for them (``dr.sync_thread``) before copying
them to numpy, so a timed run includes the whole query on either device.
"""

from __future__ import annotations

import dataclasses
import os
import time

from . import llvm

_LLVM_PROBLEM = llvm.configure()  # before drjit is imported: Dr.Jit reads DRJIT_LIBLLVM_PATH once

try:
    import drjit as dr
    import mitsuba as mi
except ImportError as exc:  # the registry turns this into Unavailable(reason=…)
    raise ImportError("mitsuba/drjit are not installed: pip install -c constraints.txt -e '.[engines]' (and, for "
                      "the CPU variant, " + llvm.INSTALL_HINT + ")") from exc

import numpy as np

from ..base import HostArrayBackend
from ..core.driver import _whole_at_least
from ..core.table import METHOD_TABLE
from ..engine import from_the_start
from ..protocol import Capabilities, Declined, Status
from . import scenes

#: isobench device → Mitsuba variant
VARIANTS = {"llvm": "llvm_ad_rgb", "cuda": "cuda_ad_rgb"}


def _devices() -> tuple[str, ...]:
    out = []
    if _LLVM_PROBLEM is None and dr.has_backend(dr.JitBackend.LLVM) and "llvm_ad_rgb" in mi.variants():
        out.append("llvm")
    if dr.has_backend(dr.JitBackend.CUDA) and "cuda_ad_rgb" in mi.variants():
        out.append("cuda")
    return tuple(out)


@dataclasses.dataclass(frozen=True)
class MitsubaSettings:
    """How Dr.Jit runs, recorded with every result (``driver_json``).  threads: Dr.Jit's CPU
    thread pool for the LLVM variant (``dr.set_thread_count``; ``--threads`` of the bench
    commands); no effect on CUDA.  ``ladder`` is unused (no knob reads it)."""

    threads: int = 1
    ladder: int = 0

    kind = "engine"

    def __post_init__(self):
        _whole_at_least(type(self).__name__, "threads", self.threads, 1)
        _whole_at_least(type(self).__name__, "ladder", self.ladder, 0)

    def record(self) -> dict:
        return {"driver": self.kind, **dataclasses.asdict(self)}


class MitsubaBackend(HostArrayBackend):
    """Mitsuba 3 on ``device`` ("llvm" or "cuda"); arrays in and out are numpy's."""

    lib = "mitsuba"
    xp = np
    capabilities = Capabilities(
        dtypes=("float32",),
        devices=_devices(),
        autodiff=None,
        jit=True,
        notes=("raycast only: Scene.ray_intersect_preliminary on an sdfgrid (closed grid SDFs) or a Mesh, float32 as "
               "Mitsuba computes; CONVERGED/MISS are the engine's answers, not certified; iterations and evals 0",
               "no dt/dθ: the grid and mesh scenes have no parameters θ, and sdfgrid's grid and to_world are "
               "non-differentiable in Mitsuba 3.9",
               "mitsuba:llvm needs libLLVM 16+ (DRJIT_LIBLLVM_PATH, set by the backend when found at a standard "
               "path); mitsuba:cuda evaluates and synchronises (dr.eval, dr.sync_thread) inside the timed run"),
    )
    settings = MitsubaSettings()
    stop_gradient = None
    _impl = {"raycast": METHOD_TABLE["raycast"]}

    def __init__(self, device: str = "llvm", settings: MitsubaSettings | None = None):
        if device not in self.capabilities.devices:
            why = f" ({_LLVM_PROBLEM})" if device == "llvm" and _LLVM_PROBLEM else ""
            raise ValueError(f"mitsuba backend: device {device!r} not available{why}; available: "
                             f"{self.capabilities.devices or 'none'} (devices: 'llvm' on the CPU, 'cuda' on a GPU)")
        super().__init__(device, settings)
        self.variant = VARIANTS[device]
        self._scenes: dict = {}
        self._built = False

    def _use(self):
        if mi.variant() != self.variant:
            mi.set_variant(self.variant)
        if self.device == "llvm" and dr.thread_count() != self.settings.threads:
            dr.set_thread_count(self.settings.threads)

    def methods(self):
        """The methods offered here (``_impl``), ``raycast`` included: the catalog leaves it to the
        engines (``MethodSpec.libs = ()``), which name it themselves."""
        return tuple(sorted(self._impl))

    def synchronize(self, out=None):
        dr.sync_thread()

    def versions(self):
        return {"mitsuba": mi.__version__, "drjit": dr.__version__, "variant": self.variant,
                **({"libLLVM": os.environ.get(llvm.ENV, "")} if self.device == "llvm" else {})}

    def declines(self, method: str, scene) -> str | None:
        return scenes.decline_reason(scene) if method == "raycast" else None

    def prepare(self, method, scene, origins, directions, *, dtype="float32", **kw):
        """:meth:`impls.base.ArrayBackend.prepare` after :meth:`declines`; builds the Mitsuba scene
        (its BVH) and compiles the query (:meth:`compile`; ``Prepared.compile_s``)."""
        if isinstance(method, str) and method in self._impl:
            reason = self.declines(method, scene)
            if reason:
                raise Declined(reason)
            if dtype != "float32":
                raise ValueError(f"raycast: dtype={dtype!r}; Mitsuba computes in float32: use dtype='float32'")
            # the rays' start o + t_min·d in float64, before they are rounded to float32
            return from_the_start(super().prepare, method, scene, origins, directions, dtype=dtype, **kw)
        return super().prepare(method, scene, origins, directions, dtype=dtype, **kw)

    def compile(self, fn, o, d, th):
        """Build the scene and compile the query by running ``fn`` on all the rays: Dr.Jit traces
        a one-ray batch as scalars (literals), so only a batch of the timed size compiles the kernel
        the timed runs reuse."""
        self._built = False
        t0 = time.perf_counter()
        fn(o, d, None)
        took = time.perf_counter() - t0
        self.last_compile_cache = "compiled" if self._built else "reused"  # (the scene, for this object)
        return fn, took

    def _scene(self, scene):
        key = (id(scene), self.variant)
        got = self._scenes.get(key)
        if got is None or got[0] is not scene:
            got = (scene, scenes.build(scene))
            self._scenes[key] = got
            self._built = True
        return got[1]

    def solve(self, method, scene, o, d, *, t_min, t_max, theta=None, **knobs):
        """The first hit in [t_min, t_max] of every ray (module docstring)."""
        if theta is not None:
            raise Declined("mitsuba evaluates scenes at their stored geometry only (no θ)")
        self._use()
        mscene = self._scene(scene)
        n = o.shape[0]
        o64, d64 = np.asarray(o, np.float64), np.asarray(d, np.float64)
        bad = ~np.all(np.isfinite(o64) & np.isfinite(d64), axis=1)
        start = np.where(bad[:, None], 0.0, o64 + t_min * d64).astype(np.float32)
        dirs = np.where(bad[:, None], 1.0, d64).astype(np.float32)
        span = t_max - t_min
        maxt = float(np.finfo(np.float32).max) if not np.isfinite(span) else float(span)
        ray = mi.Ray3f(o=mi.Point3f(start[:, 0], start[:, 1], start[:, 2]),
                       d=mi.Vector3f(dirs[:, 0], dirs[:, 1], dirs[:, 2]))
        ray.maxt = mi.Float(np.full(n, maxt, np.float32))  # an array, not a literal: one kernel for every t_max
        pi = mscene.ray_intersect_preliminary(ray)
        valid = pi.is_valid()
        si = pi.compute_surface_interaction(ray, mi.RayFlags.Minimal, valid)  # si.n: the geometric normal
        dr.eval(pi.t, valid, si.n)
        dr.sync_thread()  # the query has run (on a GPU too) before the copies below
        hit, t = np.array(valid, dtype=bool), np.array(pi.t, dtype=np.float64)
        nrm = np.stack([np.array(si.n.x), np.array(si.n.y), np.array(si.n.z)], axis=1).astype(np.float64)
        t_out = np.where(hit, t + t_min, np.inf)
        status = np.where(hit, Status.CONVERGED, Status.MISS).astype(np.int32)
        t_out[bad], status[bad] = np.nan, Status.BAD_INPUT
        from ..warp.mesh import unit_normals  # (numpy only: no Warp import)

        zeros = np.zeros(n, np.int32)
        return {"t": t_out.astype(o.dtype), "status": status, "iterations": zeros, "evals": zeros.copy(),
                "normal": unit_normals(nrm, hit & ~bad)}
