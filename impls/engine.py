"""Engine backends: a ray-tracing engine's own first-hit query as an isobench backend.

An *engine* (Embree, Open3D, …) is not an array library that runs isobench's root finders: it
intersects rays with its own geometry (a BVH over a mesh's triangles) in its own precision.  An
engine backend offers one method, ``raycast`` (:data:`impls.methods.METHODS`: family ``root``, no
knobs, ``dtypes = ("float32",)``), on triangle-mesh scenes (:class:`reference.mesh.MeshSDF`), and
*declines* every other scene (:meth:`EngineBackend.declines`, :class:`impls.protocol.Declined`
from ``prepare``), which a run records as a skipped configuration with the reason.

What an engine's answer means (the status contract of ``README.md``, "Conventions"):

* **CONVERGED is the engine's hit, not a certified one.**  isobench's root finders call a ray
  CONVERGED only on a sign-change bracket no wider than their tolerance; an engine gives no
  bracket and no error bound: its float32 ray–triangle test says "hit at t".  The status is the
  only one the protocol has for "an answer with a depth", so ``raycast`` reports it, and nothing
  more is claimed: its rows are judged by the validator against the exact float64 reference like
  every row (a false hit, a false miss, a depth error over float32's √ε · max(1, T) in the
  stability matrix).  **MISS** likewise is the engine's "no hit", not a certified miss.
* BAD_INPUT for a ray with a non-finite origin or direction component or a zero direction (the
  engine is not asked: its answer there is undefined), every float output NaN.
* No other status: an engine has no budget (MAX_ITER), evaluates no field (NON_FINITE,
  LIPSCHITZ_VIOLATED) and does not say when it is unsure (UNCERTIFIED).
* ``t`` is the engine's float32 depth, widened exactly to float64; ``iterations`` and ``evals``
  are 0 (the engine evaluates no field φ: its cost is time, not evaluations); the extra output
  ``normal`` is the engine's own normal of the hit triangle, normalised in float64 (NaN on a
  MISS).
* ``[t_min, t_max]``: the rays start at ``o + t_min·d`` (computed in float64, then rounded to
  float32 with the rest of the ray) and ``t_min`` is added back to the engine's depth; a first
  hit beyond ``t_max`` is a MISS.

The triangle geometry is built once per scene object and backend (the engine's BVH build):
``Prepared.compile_s`` is that build's time and ``compile_cache`` says whether this ``prepare``
built it ("compiled") or reused it ("reused").  ``Prepared.run`` times the ray query alone.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from .base import check_range, check_rays
from .methods import get_method
from .protocol import Capabilities, Declined, Prepared, RayResult, Status

#: the method every engine backend offers
RAYCAST = "raycast"


def from_the_start(prepare, method, scene, origins, directions, *, t_min: float = 0.0, t_max: float = math.inf,
                   **kw) -> Prepared:
    """``prepare(method, scene, origins, directions, t_min=0, t_max=t_max − t_min, **kw)`` on rays
    that start at o + t_min·d, computed in float64 before the backend rounds them to its dtype, with
    t_min added back to the depths (in float64): what :class:`EngineBackend` does for its engines,
    for a backend whose ray query goes through :meth:`impls.base.ArrayBackend.prepare` (Warp's and
    Mitsuba's ``raycast``), which rounds the rays first.  Rounded first, a start 1e6 along a float32
    ray was off by 0.06 (its spacing there): 1 false hit, 2 false misses and a depth error of 0.23
    at t_min = 1e6, where Embree and Open3D were exact to 1e-6 (probe of 2026-11-30)."""
    t_min, t_max = check_range(t_min, t_max)
    if t_min == 0.0:
        return prepare(method, scene, origins, directions, t_min=t_min, t_max=t_max, **kw)
    o, d = check_rays(origins, directions, "float64")
    with np.errstate(invalid="ignore", over="ignore"):
        start = o + t_min * d
    p = prepare(method, scene, start, d, t_min=0.0, t_max=t_max - t_min, **kw)

    def result(out) -> RayResult:
        r = p.result(out)
        r.t = np.asarray(r.t, np.float64) + t_min  # (inf and NaN stay)
        return r

    return Prepared(run=p.run, result=result, compile_s=p.compile_s, compile_cache=p.compile_cache)


def is_mesh(scene: Any) -> bool:
    """A triangle-mesh scene (:class:`reference.mesh.MeshSDF`: ``vertices``, ``faces``), by duck
    type, so that this module does not import the reference (and its mesh libraries)."""
    return getattr(scene, "kind", None) == "mesh" and hasattr(scene, "vertices") and hasattr(scene, "faces")


def engine_capabilities(notes: tuple[str, ...]) -> Capabilities:
    """float32 on the CPU, no autodiff, no compilation: what every engine backend states."""
    common = ("offers raycast only: the engine's first hit with the mesh's triangles, in float32 as the engine "
              "computes; CONVERGED and MISS are the engine's answer, not certified (no bracket, no error bound): "
              "its rows are judged against the exact float64 reference like every row",
              "declines every scene that is not a triangle mesh (reference.mesh.MeshSDF): analytic, CSG, grid, "
              "neural and user fields are skipped with the reason",
              "evals and iterations are 0 (no field evaluation); compile_s is the engine's BVH build")
    return Capabilities(dtypes=("float32",), devices=("cpu",), autodiff=None, jit=False, notes=common + notes)


class EngineBackend:
    """Protocol glue shared by the engine backends: argument checks, the geometry cache, rays in
    float32, statuses and outputs (module docstring).  A subclass sets ``lib``, ``capabilities``
    and writes :meth:`build` (the engine's scene from float32 vertices and int32 faces),
    :meth:`cast` (first hits of float32 rays: depth, inf on a miss, and the normal) and
    :meth:`versions`."""

    lib: str = ""
    capabilities: Capabilities = engine_capabilities(())

    def __init__(self, device: str = "cpu"):
        if device not in self.capabilities.devices:
            raise ValueError(f"{self.lib} backend: device {device!r} not available; available: "
                             f"{self.capabilities.devices}")
        self.device = device
        self.id = self.lib
        self._geometry: dict[int, tuple[Any, Any]] = {}  # id(scene) -> (scene kept alive, engine scene)

    def __repr__(self) -> str:
        return f"<isobench engine backend {self.id}>"

    # engine hooks ------------------------------------------------------------------------------
    def build(self, vertices: np.ndarray, faces: np.ndarray) -> Any:  # pragma: no cover
        raise NotImplementedError

    def cast(self, geometry: Any, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(depth (n,) float32, inf where no hit; normal (n, 3), any scale) of float32 rays."""
        raise NotImplementedError  # pragma: no cover

    def versions(self) -> dict[str, str]:  # pragma: no cover
        return {}

    # protocol ----------------------------------------------------------------------------------
    def methods(self) -> tuple[str, ...]:
        return (RAYCAST,)

    def synchronize(self, out: Any = None) -> None:
        """Nothing queued: the engine's query returns when its answer is done."""

    def declines(self, method: str, scene: Any) -> str | None:
        """Why ``raycast`` does not run on ``scene`` (a scene that is not a triangle mesh), or None."""
        if method == RAYCAST and not is_mesh(scene):
            return (f"{self.lib} casts rays at triangle meshes only (reference.mesh.MeshSDF); this scene is a "
                    f"{type(scene).__name__}")
        return None

    def geometry(self, scene: Any) -> tuple[Any, float, bool]:
        """The engine's scene for ``scene`` (built on first use), the build's seconds, and whether
        it was built now."""
        key = id(scene)
        if key in self._geometry and self._geometry[key][0] is scene:
            return self._geometry[key][1], 0.0, False
        v = np.ascontiguousarray(np.asarray(scene.vertices, np.float64), np.float32)
        f = np.ascontiguousarray(np.asarray(scene.faces), np.int32)
        t0 = time.perf_counter()
        geom = self.build(v, f)
        took = time.perf_counter() - t0
        self._geometry[key] = (scene, geom)
        return geom, took, True

    def prepare(self, method: str, scene: Any, origins: Any, directions: Any, *, dtype: str = "float32",
                t_min: float = 0.0, t_max: float = math.inf, t_hit: Any = None, color: Any = None,
                **knobs: Any) -> Prepared:
        """``raycast`` on ``scene`` (a mesh) for the rays, in float32 (:class:`impls.protocol.Backend`).

        Errors name the argument: a method other than ``raycast`` (NotImplementedError), a dtype
        other than float32, a knob (raycast has none), ``t_hit`` or ``color`` (ValueError), rays
        as :func:`impls.base.check_rays`; a scene that is not a mesh raises :class:`Declined`."""
        if not isinstance(method, str):
            raise TypeError(f"method must be a method name (str), got {type(method).__name__} {method!r}")
        spec = get_method(method)
        if method not in self.methods():
            raise NotImplementedError(f"backend {self.id} does not implement {method!r}; it implements {self.methods()}")
        if not (callable(getattr(scene, "value", None)) and hasattr(scene, "info")):
            raise TypeError(f"scene must be a reference.scene.Field, got {type(scene).__name__}")
        if not isinstance(dtype, str) or dtype not in self.capabilities.dtypes:
            raise ValueError(f"dtype={dtype!r} not supported by {self.id}: the engine computes in "
                             f"{self.capabilities.dtypes}; use dtype='float32'")
        t_min, t_max = check_range(t_min, t_max)
        spec.validate(knobs)  # raycast has no knobs: any knob is an error naming the valid ones
        if t_hit is not None:
            raise ValueError(f"{method} finds its own depths: pass t_hit only to methods with MethodSpec.needs_t_hit")
        if color is not None:
            raise ValueError(f"{method} does not shade: pass color only to methods with MethodSpec.needs_color")
        reason = self.declines(method, scene)
        if reason:
            raise Declined(reason)
        o, d = check_rays(origins, directions, dtype)
        bad = ~(np.all(np.isfinite(o), axis=1) & np.all(np.isfinite(d), axis=1))
        start = o + t_min * d if t_min != 0.0 else o
        # rays the engine is not asked about (BAD_INPUT) get a harmless stand-in
        o32 = np.ascontiguousarray(np.where(bad[:, None], 0.0, start), np.float32)
        d32 = np.ascontiguousarray(np.where(bad[:, None], [1.0, 0.0, 0.0], d), np.float32)
        geom, build_s, built = self.geometry(scene)

        def run() -> tuple[np.ndarray, np.ndarray]:
            return self.cast(geom, o32, d32)

        def result(out: tuple[np.ndarray, np.ndarray]) -> RayResult:
            depth, normal = out
            t = np.asarray(depth, np.float32).astype(np.float64) + t_min
            hit = np.isfinite(t) & (t <= t_max) & ~bad
            status = np.where(bad, Status.BAD_INPUT, np.where(hit, Status.CONVERGED, Status.MISS)).astype(np.int32)
            t = np.where(hit, t, np.where(bad, np.nan, np.inf))
            nrm = np.asarray(normal, np.float64).reshape(-1, 3)
            with np.errstate(invalid="ignore", divide="ignore"):
                nrm = nrm / np.linalg.norm(nrm, axis=1, keepdims=True)
            nrm = np.where(hit[:, None], nrm, np.nan)
            zero = np.zeros(len(t), np.int32)
            return RayResult(t=t, status=status, iterations=zero, evals=zero.copy(), outputs={"normal": nrm})

        return Prepared(run=run, result=result, compile_s=build_s, compile_cache="compiled" if built else "reused")
