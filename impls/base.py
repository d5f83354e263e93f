"""Shared machinery of the built-in backends (the protocol itself is in ``protocol.py``)."""

from __future__ import annotations

import math
import time
from typing import Any, Callable

import numpy as np

from .methods import get_method
from .protocol import Capabilities, Prepared, RayResult


def check_rays(origins: Any, directions: Any) -> tuple[np.ndarray, np.ndarray]:
    """Validate ray arrays (float64 numpy, shape (n, 3), finite, unit directions)."""
    o = np.asarray(origins, dtype=np.float64)
    d = np.asarray(directions, dtype=np.float64)
    if o.ndim != 2 or o.shape[1] != 3:
        raise ValueError(f"origins must have shape (n, 3), got {o.shape}; reshape with origins.reshape(-1, 3)")
    if d.shape != o.shape:
        raise ValueError(f"directions must have the shape of origins {o.shape}, got {d.shape}")
    dn = np.linalg.norm(d, axis=1)
    if not np.all(np.abs(dn - 1) < 1e-12):
        raise ValueError("directions must be unit vectors; normalise them with d / np.linalg.norm(d, axis=1, keepdims=True)")
    return o, d


def check_color(method: str, color: Any) -> Any:
    """The colour field a render method shades with: ``color`` if it has ``value(x, xp)``, the
    default :class:`reference.rendering.SineColor` if ``None``."""
    if color is None:
        from reference.rendering import SineColor

        return SineColor()
    if not callable(getattr(color, "value", None)):
        raise ValueError(f"{method}: color must be a colour field with value(x, xp) -> (..., 3) (e.g. "
                         f"reference.rendering.SineColor() or case.color_field), got {type(color).__name__}")
    return color


class ArrayBackend:
    """Base of the built-in backends: validation, method lookup, ``prepare``.

    Subclasses set ``lib``, ``capabilities``, ``xp`` and ``_impl`` (name → function of
    ``(backend, scene, o, d, *, t_min, t_max, t_hit, **knobs)`` (plus ``color=`` for methods with
    ``MethodSpec.needs_color``) returning a dict of native
    arrays with at least ``t, status, iterations, evals``; ``t_hit`` is ``None`` or the
    per-ray depth (native array) that point-wise methods (normals, curvature, dt/dθ) evaluate
    at) and implement ``asarray``, ``to_numpy``, ``synchronize`` and optionally ``compile``.
    """

    lib: str = ""
    capabilities = Capabilities()
    xp: Any = None
    _impl: dict[str, Callable] = {}

    def __init__(self, device: str = "cpu"):
        if device not in self.capabilities.devices:
            raise ValueError(f"{self.lib} backend: device {device!r} not available; available: {self.capabilities.devices}")
        self.device = device
        self.id = self.lib if self.lib == "numpy" else f"{self.lib}:{device}"

    def __repr__(self) -> str:
        return f"<isobench backend {self.id}>"

    def methods(self) -> tuple[str, ...]:
        return tuple(sorted(self._impl))

    # subclasses ------------------------------------------------------------------------------
    def asarray(self, a: np.ndarray, dtype: str) -> Any:  # pragma: no cover
        raise NotImplementedError

    def to_numpy(self, a: Any) -> np.ndarray:  # pragma: no cover
        raise NotImplementedError

    def synchronize(self, out: Any = None) -> None:
        """Block until device work (of ``out``, or all queued work) is done."""

    def compile(self, fn: Callable, *example_args: Any) -> tuple[Callable, float | None]:
        """Compile ``fn`` for ``example_args``; returns (callable, compile seconds or None)."""
        return fn, None

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
        spec = get_method(method)
        if method not in self._impl:
            raise NotImplementedError(f"backend {self.id} does not implement {method!r}; it implements {self.methods()}")
        if dtype not in self.capabilities.dtypes:
            raise ValueError(f"dtype={dtype!r} not supported by {self.id}; use one of {self.capabilities.dtypes}")
        reason = spec.skip_reason(scene)
        if reason:
            raise ValueError(reason)
        if not (t_min < t_max):
            raise ValueError(f"t_min={t_min} must be < t_max={t_max}")
        knobs = spec.validate(knobs)
        extra = {"color": check_color(method, color)} if spec.needs_color else {}
        if color is not None and not spec.needs_color:
            raise ValueError(f"{method} does not shade: pass color only to methods with MethodSpec.needs_color "
                             f"({spec.family} family methods take none)")
        o_np, d_np = check_rays(origins, directions)
        if spec.needs_t_hit:
            if t_hit is None:
                raise ValueError(f"{method} evaluates at given hits: pass t_hit (per-ray depth, shape (n,))")
            t_hit = np.asarray(t_hit, dtype=np.float64)
            if t_hit.shape != (o_np.shape[0],):
                raise ValueError(f"t_hit must have shape ({o_np.shape[0]},), got {t_hit.shape}")
        o, d = self.asarray(o_np, dtype), self.asarray(d_np, dtype)
        th = None if t_hit is None else self.asarray(t_hit, dtype)
        impl = self._impl[method]

        def fn(o, d, th):
            return impl(self, scene, o, d, t_min=float(t_min), t_max=float(t_max), t_hit=th, **extra, **knobs)

        run_fn, compile_s = self.compile(fn, o, d, th)

        def result(out: Any) -> RayResult:
            out = {k: self.to_numpy(v) for k, v in out.items()}
            return RayResult(t=out.pop("t").astype(np.float64), status=out.pop("status").astype(np.int32),
                             iterations=out.pop("iterations").astype(np.int32), evals=out.pop("evals").astype(np.int32),
                             outputs=out)

        return Prepared(run=lambda: run_fn(o, d, th), result=result, compile_s=compile_s)


def timed_compile(compile_thunk: Callable[[], Callable]) -> tuple[Callable, float]:
    t0 = time.perf_counter()
    fn = compile_thunk()
    return fn, time.perf_counter() - t0
