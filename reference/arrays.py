"""Array-API helpers shared by the scene nodes and the ray bounds.

Everything a node's φ, or a bound of :mod:`reference.raybounds`, computes with goes through the
caller's namespace ``xp`` (https://data-apis.org/array-api/): numpy, ``array_api_compat.torch``
or ``jax.numpy``.  These helpers are the few operations written once for all of them: constants
in the caller's dtype and device (:func:`const`), sums, maxima and Euclidean norms over the short
coordinate axis (:func:`sum_last`, :func:`max_last`, :func:`norm`, :func:`safe_norm`), and the
identification of an array's library and dtype for error messages (:func:`_array_lib`,
:func:`_is_real_floating`).  This module imports nothing of ``reference``, so every module of it
can build on this one without an import cycle; :mod:`reference.scene` re-exports the names.
"""

from __future__ import annotations

from typing import Any

import numpy as np


_CONSTS: dict = {}
_CONSTS_MAX = 4096


def _const(xp: Any, like: Any, value: Any) -> Any:
    """``value`` as an array of ``like``'s namespace, dtype and device.

    torch tensors are cached per (dtype, device, value): creating one costs microseconds per
    call, about 8% of a torus ∪ box φ on the root finders' few-ray straggler steps
    (cProfile), where φ is called thousands of times with the same constants.  The cache
    holds at most ``_CONSTS_MAX`` entries (cleared when full); cached tensors are never
    written to.  (jax traces φ once per compilation, and a cached array made while tracing
    could leak a tracer, so jax is not cached.)"""
    import array_api_compat

    if xp is np or array_api_compat.is_numpy_array(like):
        return np.asarray(value, dtype=like.dtype)
    if not array_api_compat.is_torch_array(like):
        return xp.asarray(value, dtype=like.dtype, device=array_api_compat.device(like))
    v = np.asarray(value, dtype=np.float64)
    key = (like.dtype, like.device, v.shape, v.tobytes())  # bytes: −0.0 and 0.0 stay apart
    out = _CONSTS.get(key)
    if out is None:
        if len(_CONSTS) >= _CONSTS_MAX:
            _CONSTS.clear()
        out = _CONSTS[key] = xp.asarray(v, dtype=like.dtype, device=like.device)
    return out


def const(xp: Any, like: Any, value: Any) -> Any:
    """Public form of :func:`_const` for node implementations (non-parameter constants)."""
    return _const(xp, like, value)


def _fold_last(v: Any, op: Any) -> Any:
    """op(…op(op(v[..., 0], v[..., 1]), v[..., 2])…) over the last axis."""
    out = v[..., 0]
    for i in range(1, v.shape[-1]):
        out = op(out, v[..., i])
    return out


def sum_last(xp: Any, v: Any) -> Any:
    """Σ over the (short, coordinate) last axis as the explicit adds v[..., 0] + v[..., 1] + …,
    not ``xp.sum(v, axis=-1)``: numpy loops over one short axis per output, and XLA on the CPU
    emits a reduction over it that does not vectorise, where the adds are elementwise over
    whole rows; torch is no slower either way.  The adds are elementwise operations, which also run on
    contiguous rows of the root finders' structure-of-arrays views (:mod:`impls.core.driver`)."""
    return _fold_last(v, xp.add)


def max_last(xp: Any, v: Any) -> Any:
    """max over the (short, coordinate) last axis as elementwise maxima (see :func:`sum_last`)."""
    return _fold_last(v, xp.maximum)


def norm(xp: Any, v: Any) -> Any:
    """Euclidean norm over the last axis, written with array-API primitives only."""
    return xp.sqrt(sum_last(xp, v * v))


def safe_norm(xp: Any, v: Any) -> Any:
    """Euclidean norm whose autodiff gradient is 0 (not NaN) where v = 0.

    The "double where" keeps √ away from 0 in the traced graph, so the value is exactly |v|
    and reverse-mode through the unused branch sees a finite derivative.  Used where an SDF
    evaluates |max(q, 0)| with q ≤ 0 on the surface itself (box, capped cylinder).  numpy
    arrays, which nothing differentiates, take the plain √ (the same value; 3 of a box φ's 20
    array operations fewer)."""
    s = sum_last(xp, v * v)
    if isinstance(s, np.ndarray) and s.dtype.kind == "f":  # (object arrays: the mpmath references')
        return xp.sqrt(s)
    pos = s > 0
    return xp.where(pos, xp.sqrt(xp.where(pos, s, const(xp, s, 1.0))), const(xp, s, 0.0))


def unit(v: np.ndarray) -> np.ndarray:
    """Rows of ``v`` divided by their Euclidean norm (float64 numpy)."""
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _array_lib(a: Any) -> str:
    """The array library of ``a`` ("numpy", "torch", "jax", or its type's name for anything else)."""
    import array_api_compat

    if isinstance(a, (np.ndarray, np.generic)):
        return "numpy"
    if array_api_compat.is_torch_array(a):
        return "torch"
    if array_api_compat.is_jax_array(a):
        return "jax"
    return type(a).__name__


def _is_real_floating(a: Any) -> bool:
    dt = a.dtype
    if getattr(dt, "is_floating_point", None) is not None:  # torch.dtype
        return dt.is_floating_point and not dt.is_complex
    return np.dtype(dt).kind == "f"
