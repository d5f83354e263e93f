"""Shared machinery of the built-in backends (the protocol itself is in ``protocol.py``)."""

from __future__ import annotations

import dataclasses
import math
import numbers
import time
from typing import Any, Callable

import numpy as np

from reference.rays import unit_directions, unit_tolerance

from .core.methods_root import step_field
from .core.param_grad import python_fori, python_switch
from .core.rootfind import void_if_refuted
from .core.table import METHOD_TABLE
from .methods import get_method
from .protocol import Capabilities, Prepared, RayResult


def _real_rows(a: Any, name: str) -> np.ndarray:
    """``a`` as a numpy array of real numbers (float or integer dtype), or a TypeError/ValueError
    naming ``name``."""
    try:
        arr = np.asarray(a)
    except Exception as exc:  # ragged lists, tensors that need .detach(), …
        raise TypeError(f"{name} must be an array of real numbers of shape (n, 3); np.asarray({name}) failed: "
                        f"{type(exc).__name__}: {exc}") from None
    if arr.dtype.kind not in "fiu":
        hint = " (take the real part explicitly if that is meant)" if arr.dtype.kind == "c" else ""
        raise TypeError(f"{name} must be an array of real numbers (float or integer dtype), got dtype {arr.dtype}{hint}")
    return arr


def check_rays(origins: Any, directions: Any, dtype: str = "float64") -> tuple[np.ndarray, np.ndarray]:
    """Validate ray arrays; returns float64 numpy copies of shape (n, 3), n ≥ 1.

    Whole-call errors (ValueError/TypeError naming ``origins`` or ``directions``): not real
    numbers, wrong shape, mismatched counts, or a finite non-zero direction that is not unit
    within :func:`reference.rays.unit_tolerance` of the given arrays' dtype and the run ``dtype`` (float32
    directions normalised in float32 pass; the message gives the worst ray and the fix).

    Per-ray errors (flagged ``Status.BAD_INPUT`` by every method, outputs NaN): a non-finite
    origin or direction component, or a zero direction — returned with that direction set to NaN,
    so that one test (``rootfind.bad_rays``: any component non-finite) flags all of them.

    A direction accepted within a coarser dtype's tolerance than float64's (normalised in float32:
    ‖d‖ − 1 up to ~1e-7) is normalised again in float64, d / ‖d‖, and that is the ray solved: the
    depths t, t_min and t_max are distances along it (:func:`reference.rays.unit_directions`; a
    1e-5 shell seen from 1,000 away had 1,746 of 4,000 rays CONVERGED on its far side before).
    Directions unit to float64's rounding are returned as given, bit for bit."""
    o_in, d_in = _real_rows(origins, "origins"), _real_rows(directions, "directions")
    o = np.array(o_in, dtype=np.float64)  # copies: the zero-direction rows below are overwritten
    d = np.array(d_in, dtype=np.float64)
    if o.ndim != 2 or o.shape[1] != 3 or o.shape[0] == 0:
        raise ValueError(f"origins must have shape (n, 3) with n ≥ 1, got {o.shape}; reshape with origins.reshape(-1, 3)")
    if d.shape != o.shape:
        raise ValueError(f"directions must have the shape of origins {o.shape}, got {d.shape} (one direction per origin)")
    finite = np.all(np.isfinite(d), axis=1)
    with np.errstate(over="ignore"):
        dn = np.linalg.norm(np.where(finite[:, None], d, 0.0), axis=1)
    d[finite & (dn == 0)] = np.nan
    d = unit_directions(d, unit_tolerance(d_in.dtype, dtype), "directions",
                        f"{d_in.dtype} directions and dtype={dtype!r}")
    return o, d


def check_range(t_min: Any, t_max: Any) -> tuple[float, float]:
    """[t_min, t_max] as floats: real numbers (not bool), t_min finite, t_max > t_min (may be +inf)."""
    out = []
    for name, v in (("t_min", t_min), ("t_max", t_max)):
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, numbers.Real):
            raise TypeError(f"{name} must be a real number, got {type(v).__name__} {v!r}")
        out.append(float(v))
    lo, hi = out
    if not math.isfinite(lo):
        raise ValueError(f"t_min={t_min!r} must be finite (the depth where every ray's search starts)")
    if not (lo < hi):
        raise ValueError(f"t_min={t_min!r} must be < t_max={t_max!r} (t_max may be inf; NaN is not a depth)")
    return lo, hi


def check_color(method: str, color: Any) -> Any:
    """The colour field a render method shades with: ``color`` if it has ``value(x, xp)``, the
    default :class:`reference.rendering.SineColor` if ``None``."""
    if color is None:
        from reference.rendering import SineColor

        return SineColor()
    if not callable(getattr(color, "value", None)):
        raise ValueError(f"{method}: color must be a colour field with value(x, xp) -> (..., 3) (e.g. "
                         f"reference.rendering.SineColor() or case.color_field), got {type(color).__name__}")
    from reference.rendering import CheckedColor, SineColor

    # the library's own field is trusted; a user's is checked on every output (CheckedColor)
    return color if isinstance(color, (SineColor, CheckedColor)) else CheckedColor(color)


def _join_rows(xp: Any, parts: list) -> Any:
    """Blocks' outputs (arrays, or tuples or dicts of them) joined along their first axis."""
    first = parts[0]
    if isinstance(first, dict):
        return {k: xp.concat([p[k] for p in parts]) for k in first}
    if isinstance(first, tuple):
        return tuple(xp.concat([p[i] for p in parts]) for i in range(len(first)))
    return xp.concat(parts)


class ArrayBackend:
    """One array library's hooks; everything else is shared (validation, ``prepare``, the method
    table :data:`impls.core.table.METHOD_TABLE`, built once from the catalog).

    A subclass sets ``lib``, ``capabilities``, ``xp`` (its array-API namespace) and ``settings``
    (its loop driver's settings: a frozen dataclass with ``ladder`` and ``record()``, recorded
    with every result), and implements the hooks:

    * ``asarray(a, dtype)``, ``to_numpy(a)``, ``synchronize(out)``, ``versions()``, optionally
      ``compile(fn, *args)`` and ``compile_configuration`` (one kernel shared by configurations
      that differ only in knobs: jax);
    * ``ray_eval(scene, theta)`` → ``ev(o, d, t, deriv) -> (φ, dφ/dt or None, cost)`` along rays;
    * ``grad_hess(scene, x, hess, theta=None)`` → ``(∇φ, Hessian or None, cost)`` at points;
    * ``theta_jacobian(fun, theta)`` → ``(J, cost)``, the Jacobian (n, P) of θ ↦ fun(θ) (n,);
    * ``run_loop(alg, o, d, ev)`` → the outputs of a root finder (:mod:`impls.core.rootfind`)
      run to completion on every ray, with ``settings``;
    * ``stop_gradient`` (``None``: no autodiff, ``render_surface`` is ρ at the hit itself),
      ``compact`` (volume rendering drops terminated rays), ``fori_loop`` (the unrolled tracer's
      loop, ``lax.fori_loop`` semantics), ``switch`` (a branch chosen by an index, ``lax.switch``
      semantics: a volume renderer's density model, :class:`impls.core.rendering.DensityChoice`),
      ``map_rays`` (a function over blocks of rays: the default loops over them, which any array
      library can run; jax maps them inside its kernel).

    ``cost`` counts φ evaluations per point or ray (autodiff: 1; central differences: more).
    """

    lib: str = ""
    capabilities = Capabilities()
    xp: Any = None
    settings: Any = None
    stop_gradient: Callable[[Any], Any] | None = None
    compact: bool = True
    fori_loop = staticmethod(python_fori)
    switch = staticmethod(python_switch)
    _impl = METHOD_TABLE

    def __init__(self, device: str = "cpu", settings: Any = None):
        if device not in self.capabilities.devices:
            raise ValueError(f"{self.lib} backend: device {device!r} not available; available: {self.capabilities.devices}")
        self.device = device
        self.id = self.lib if self.lib == "numpy" else f"{self.lib}:{device}"
        if settings is not None:
            self.settings = settings

    def __repr__(self) -> str:
        return f"<isobench backend {self.id}>"

    def methods(self) -> tuple[str, ...]:
        """The catalog's methods this backend offers: all, less those whose ``MethodSpec.libs``
        names other array libraries (e.g. ``march_chandrupatla``, numpy only)."""
        return tuple(sorted(m for m in self._impl if get_method(m).libs is None or self.lib in get_method(m).libs))

    def configure(self, **changes: Any) -> None:
        """Change driver settings of this backend (``backend.configure(threads=2)``); a name its
        driver does not have is a ValueError listing those it has."""
        names = {f.name for f in dataclasses.fields(self.settings)}
        unknown = sorted(set(changes) - names)
        if unknown:
            raise ValueError(f"{self.id}: driver settings {unknown} unknown; {type(self.settings).__name__} has "
                             f"{sorted(names)}")
        self.settings = dataclasses.replace(self.settings, **changes)

    def solve(self, method: str, scene: Any, o: Any, d: Any, *, t_min: float, t_max: float, theta: Any = None,
              **knobs: Any) -> dict:
        """Root method ``method`` on rays ``o``, ``d`` (native arrays) with validated ``knobs``:
        its algorithm (``MethodSpec.algorithm``) run by this backend's loop driver, its certificates
        withdrawn where a ray refuted a bound taken on trust (:func:`impls.core.rootfind.void_if_refuted`).
        At the stored parameters it marches on the scene's step field
        (:func:`impls.core.methods_root.step_field`: the same surface, CSG operands at their own bounds)."""
        if theta is None:
            scene = step_field(scene)
        alg = get_method(method).algorithm(scene, t_min, t_max, knobs, theta, ladder=self.settings.ladder)
        return void_if_refuted(alg, self.run_loop(alg, o, d, self.ray_eval(scene, theta)))

    # hooks -----------------------------------------------------------------------------------
    def asarray(self, a: np.ndarray, dtype: str) -> Any:  # pragma: no cover
        raise NotImplementedError

    def to_numpy(self, a: Any) -> np.ndarray:  # pragma: no cover
        raise NotImplementedError

    def ray_eval(self, scene: Any, theta: Any = None) -> Callable:  # pragma: no cover
        raise NotImplementedError

    def grad_hess(self, scene: Any, x: Any, hess: bool, theta: Any = None) -> tuple:  # pragma: no cover
        raise NotImplementedError

    def theta_jacobian(self, fun: Callable, theta: Any) -> tuple:  # pragma: no cover
        raise NotImplementedError

    def run_loop(self, alg: Any, o: Any, d: Any, ev: Callable) -> dict:  # pragma: no cover
        raise NotImplementedError

    def map_rays(self, fn: Callable, arrays: tuple, rows: int) -> Any:
        """``fn(*arrays)`` computed on blocks of at most ``rows`` rays and joined: ``arrays`` have
        rays first (``None`` passes as is), ``fn``'s output is an array, or a tuple or dict of
        arrays, with rays first, each ray's row computed from that ray's rows alone (so the
        blocks give the rows the whole batch gives).  It bounds a method's memory
        (:data:`impls.core.rendering.BLOCK_SAMPLES`).  Eager backends loop over the blocks; jax maps
        them with ``lax.map`` inside its kernel."""
        n = next(a.shape[0] for a in arrays if a is not None)
        if n <= rows:
            return fn(*arrays)
        parts = [fn(*(None if a is None else a[i:i + rows] for a in arrays)) for i in range(0, n, rows)]
        return _join_rows(self.xp, parts)

    #: ``fn`` runs eagerly on each block's slices (a block's arrays are values: a renderer may read
    #: its first ray's index to draw that block's random numbers); an override that maps the blocks
    #: inside a kernel (jax) does not have it
    map_rays.loops_over_slices = True

    def synchronize(self, out: Any = None) -> None:
        """Block until device work (of ``out``, or all queued work) is done."""

    #: set by :meth:`compile` where the backend knows: "compiled" or "reused" (``Prepared.compile_cache``)
    last_compile_cache: str | None = None

    def compile(self, fn: Callable, *example_args: Any) -> tuple[Callable, float | None]:
        """Compile ``fn`` for ``example_args``; returns (callable, compile seconds or None)."""
        return fn, None

    def compile_configuration(self, call: Callable, knobs: dict, o: Any, d: Any, th: Any, **structure: Any
                              ) -> tuple[Callable, float | None]:
        """Compile one configuration: ``call(o, d, th, knobs)`` runs the method; returns
        (``run(o, d, th)``, compile seconds or None).  ``structure`` names what else the
        configuration is bound to (``method``, ``scene``, ``t_range``, ``extra``), for a backend
        that shares one kernel between configurations differing only in knobs (jax); the default
        compiles each configuration on its own with :meth:`compile`."""
        return self.compile(lambda o, d, th: call(o, d, th, knobs), o, d, th)

    def versions(self) -> dict[str, str]:
        return {}

    # protocol --------------------------------------------------------------------------------
    def prepare(self, method: str, scene: Any, origins: Any, directions: Any, *, dtype: str = "float64",
                t_min: float = 0.0, t_max: float = math.inf, t_hit: Any = None, color: Any = None,
                **knobs: Any) -> Prepared:
        """Bind ``method`` to a scene, rays, dtype and knobs (see :class:`impls.protocol.Backend`).

        ``color``: the colour field ρ of render methods (``MethodSpec.needs_color``), any object
        with ``value(x, xp) -> (..., 3)`` written against the array namespace ``xp``; ``None``
        means :class:`reference.rendering.SineColor` ``()``.  Passing it to a method that does not
        shade is a ValueError (it would be silently ignored otherwise)."""
        if not isinstance(method, str):
            raise TypeError(f"method must be a method name (str), got {type(method).__name__} {method!r}")
        spec = get_method(method)
        if not (callable(getattr(scene, "value", None)) and hasattr(scene, "info")):
            raise TypeError(f"scene must be a reference.scene.Field (a scene tree, or a CallableField wrapping "
                            f"fn(x, xp)), got {type(scene).__name__}")
        if method not in self.methods():
            raise NotImplementedError(f"backend {self.id} does not implement {method!r}; it implements {self.methods()}")
        if not isinstance(dtype, str) or dtype not in self.capabilities.dtypes:
            raise ValueError(f"dtype={dtype!r} not supported by {self.id}; use one of {self.capabilities.dtypes}")
        reason = spec.skip_reason(scene)
        if reason:
            raise ValueError(reason)
        t_min, t_max = check_range(t_min, t_max)
        if spec.finite_range and not math.isfinite(t_max):
            raise ValueError(f"{method} samples the whole interval [t_min, t_max] and t_max={t_max!r}: pass a finite "
                             "t_max (the far end of the rendered interval, e.g. where the scene's bounding ball ends)")
        knobs = spec.validate(knobs)
        extra = {"color": check_color(method, color)} if spec.needs_color else {}
        if color is not None and not spec.needs_color:
            raise ValueError(f"{method} does not shade: pass color only to methods with MethodSpec.needs_color "
                             f"({spec.family} family methods take none)")
        o_np, d_np = check_rays(origins, directions, dtype)
        if spec.needs_t_hit:
            if t_hit is None:
                raise ValueError(f"{method} evaluates at given hits: pass t_hit (per-ray depth, shape (n,))")
            t_hit = np.asarray(_real_rows(t_hit, "t_hit"), dtype=np.float64)
            if t_hit.shape != (o_np.shape[0],):
                raise ValueError(f"t_hit must have shape ({o_np.shape[0]},), got {t_hit.shape}")
        elif t_hit is not None:
            raise ValueError(f"{method} finds its own depths: pass t_hit only to methods with MethodSpec.needs_t_hit "
                             "(it would be ignored otherwise)")
        o, d = self.asarray(o_np, dtype), self.asarray(d_np, dtype)
        th = None if t_hit is None else self.asarray(t_hit, dtype)
        impl = self._impl[method]

        def call(o, d, th, knobs):
            return impl(self, scene, o, d, t_min=float(t_min), t_max=float(t_max), t_hit=th, **extra, **knobs)

        self.last_compile_cache = None  # compile() may say whether it reused a kernel
        run_fn, compile_s = self.compile_configuration(call, knobs, o, d, th, method=method, scene=scene,
                                                       t_range=(float(t_min), float(t_max)), extra=extra)
        compile_cache = self.last_compile_cache

        def result(out: Any) -> RayResult:
            out = {k: self.to_numpy(v) for k, v in out.items()}
            return RayResult(t=out.pop("t").astype(np.float64), status=out.pop("status").astype(np.int32),
                             iterations=out.pop("iterations").astype(np.int32), evals=out.pop("evals").astype(np.int32),
                             outputs=out)

        return Prepared(run=lambda: run_fn(o, d, th), result=result, compile_s=compile_s, compile_cache=compile_cache)


def timed_compile(compile_thunk: Callable[[], Callable]) -> tuple[Callable, float]:
    t0 = time.perf_counter()
    fn = compile_thunk()
    return fn, time.perf_counter() - t0


class HostArrayBackend(ArrayBackend):
    """An :class:`ArrayBackend` whose native arrays are C-contiguous numpy arrays on the host: numpy's
    own, and the backends whose compiled kernels or engines take numpy arrays (numba, Warp, Mitsuba)."""

    def asarray(self, a: np.ndarray, dtype: str) -> np.ndarray:
        return np.ascontiguousarray(a, dtype=np.dtype(dtype))

    def to_numpy(self, a: Any) -> np.ndarray:
        return np.asarray(a)

