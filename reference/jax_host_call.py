"""A numpy function of points as a jax custom call that jax's persistent compilation cache keeps.

``host_call(name, fn, x, n_out)`` runs ``fn(points) -> (array, …)`` (float64 numpy in, float64
numpy out) inside a jitted program on the CPU, as an XLA FFI custom call whose target is named
``name``.  The meshes' jax φ (:mod:`reference.mesh`) is one: the closest-point queries run in
libigl/trimesh on the host.

Why not ``jax.pure_callback``: jax never writes a program with a Python callback to its
persistent compilation cache (``jax/_src/compiler.py:_cache_write`` skips any program with host
callbacks: the callback is a live Python object baked into the executable), so every run compiled
the mesh cases' kernels afresh, 1.2–3 s each — half of a warm catalog sweep's time.  A custom
call names its target by a string: the compiled program refers to ``name`` and is cached like any
other, and each process registers the target before it traces the program (the first
:func:`host_call` with that name registers it, and tracing comes before loading a cached
executable).  So ``name`` must identify the function's *content* (the meshes use their data's
SHA-256): a cached program calls whatever is registered under its name.

Why ctypes and not a compiled extension: the harness installs no compiler, and jax ships only the
C header of its FFI (``jax.ffi.include_dir()``, ``xla/ffi/api/c_api.h``).  The target is a
``ctypes`` function pointer into Python (ctypes takes the GIL for the call) implementing the typed
FFI's calling convention at API version 0.1: it answers the metadata query XLA makes when the
target is registered, reads the argument buffers (``XLA_FFI_Buffer``: dtype, data, rank, dims)
and writes the result buffers at the execute stage; a Python exception becomes an
``XLA_FFI_Error`` (``XLA_FFI_Api.XLA_FFI_Error_Create``) with its message, which jax raises.  The
structures read here are the leading fields of c_api.h's, which later API versions only append
to.

Where jax's default backend is not the CPU (a GPU machine), :func:`host_call` uses
``jax.pure_callback`` instead (a CPU custom call cannot run in a GPU program): correct, compiled
on every run as before.
"""

from __future__ import annotations

import ctypes
import threading
from typing import Callable

import numpy as np

#: XLA_FFI_DataType codes of the float dtypes a point array may have (c_api.h)
_DTYPES = {11: np.float32, 12: np.float64}
_EXTENSION_METADATA = 1  # XLA_FFI_Extension_Metadata
_STAGE_EXECUTE = 3  # XLA_FFI_ExecutionStage_EXECUTE
_ERROR_INTERNAL = 13  # XLA_FFI_Error_Code_INTERNAL


class _ExtensionBase(ctypes.Structure):
    _fields_ = [("struct_size", ctypes.c_size_t), ("type", ctypes.c_int), ("next", ctypes.c_void_p)]


class _ApiVersion(ctypes.Structure):
    _fields_ = [("struct_size", ctypes.c_size_t), ("extension_start", ctypes.c_void_p),
                ("major_version", ctypes.c_int), ("minor_version", ctypes.c_int)]


class _Metadata(ctypes.Structure):
    _fields_ = [("struct_size", ctypes.c_size_t), ("api_version", _ApiVersion), ("traits", ctypes.c_uint32),
                ("state_type_id", ctypes.c_int64)]


class _MetadataExtension(ctypes.Structure):
    _fields_ = [("extension_base", _ExtensionBase), ("metadata", ctypes.POINTER(_Metadata))]


class _Buffer(ctypes.Structure):
    _fields_ = [("struct_size", ctypes.c_size_t), ("extension_start", ctypes.c_void_p), ("dtype", ctypes.c_int),
                ("data", ctypes.c_void_p), ("rank", ctypes.c_int64), ("dims", ctypes.POINTER(ctypes.c_int64))]


class _Args(ctypes.Structure):  # XLA_FFI_Args and XLA_FFI_Rets have the same layout
    _fields_ = [("struct_size", ctypes.c_size_t), ("extension_start", ctypes.c_void_p), ("size", ctypes.c_int64),
                ("types", ctypes.c_void_p), ("args", ctypes.POINTER(ctypes.c_void_p))]


class _ErrorCreateArgs(ctypes.Structure):
    _fields_ = [("struct_size", ctypes.c_size_t), ("extension_start", ctypes.c_void_p), ("message", ctypes.c_char_p),
                ("errc", ctypes.c_int)]


_ERROR_CREATE = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.POINTER(_ErrorCreateArgs))


class _Api(ctypes.Structure):  # the leading fields of XLA_FFI_Api
    _fields_ = [("struct_size", ctypes.c_size_t), ("extension_start", ctypes.c_void_p), ("api_version", _ApiVersion),
                ("internal_api", ctypes.c_void_p), ("error_create", _ERROR_CREATE)]


class _CallFrame(ctypes.Structure):  # the leading fields of XLA_FFI_CallFrame
    _fields_ = [("struct_size", ctypes.c_size_t), ("extension_start", ctypes.c_void_p), ("api", ctypes.POINTER(_Api)),
                ("ctx", ctypes.c_void_p), ("stage", ctypes.c_int), ("args", _Args), ("rets", _Args)]


_HANDLER = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.POINTER(_CallFrame))

#: name → (ctypes handler, capsule, fn): registered targets, kept alive for the process's life
_TARGETS: dict[str, tuple] = {}
#: how many times :func:`host_call` has been traced in this process (:func:`traced_calls`)
_CALLS = [0]
_LOCK = threading.Lock()


def _array(buf: _Buffer) -> np.ndarray:
    """A numpy view of an FFI buffer (no copy)."""
    dtype = _DTYPES.get(buf.dtype)
    if dtype is None:
        raise TypeError(f"host_call: buffer dtype code {buf.dtype} is not float32 (11) or float64 (12)")
    shape = tuple(buf.dims[i] for i in range(buf.rank))
    if not buf.data or 0 in shape:
        return np.zeros(shape, dtype)
    n = int(np.prod(shape, dtype=np.int64)) if shape else 1
    flat = np.ctypeslib.as_array(ctypes.cast(buf.data, ctypes.POINTER(np.ctypeslib.as_ctypes_type(dtype))), (n,))
    return flat.reshape(shape)


def _handler(name: str, fn: Callable):
    def handle(frame_p):
        frame = frame_p.contents
        try:
            if frame.extension_start:  # the metadata query made when the target is registered
                ext = ctypes.cast(frame.extension_start, ctypes.POINTER(_ExtensionBase)).contents
                if ext.type == _EXTENSION_METADATA:
                    md = ctypes.cast(frame.extension_start, ctypes.POINTER(_MetadataExtension)).contents.metadata.contents
                    md.api_version.major_version, md.api_version.minor_version, md.traits = 0, 1, 0
                return None
            if frame.stage != _STAGE_EXECUTE:
                return None
            args = [_array(ctypes.cast(frame.args.args[i], ctypes.POINTER(_Buffer)).contents)
                    for i in range(frame.args.size)]
            rets = [_array(ctypes.cast(frame.rets.args[i], ctypes.POINTER(_Buffer)).contents)
                    for i in range(frame.rets.size)]
            outs = fn(*(np.asarray(a, np.float64) for a in args))
            if len(outs) != len(rets):
                raise ValueError(f"returned {len(outs)} arrays for {len(rets)} results")
            for r, v in zip(rets, outs):
                r[...] = np.broadcast_to(np.asarray(v), r.shape)  # (a shape mismatch raises)
            return None
        except BaseException as exc:  # noqa: BLE001 - becomes the program's error, which jax raises
            msg = f"{name}: {type(exc).__name__}: {exc}".encode("utf-8", "replace")
            err = _ErrorCreateArgs(ctypes.sizeof(_ErrorCreateArgs), None, msg, _ERROR_INTERNAL)
            return frame.api.contents.error_create(ctypes.byref(err))

    return _HANDLER(handle)


def _register(name: str, fn: Callable) -> None:
    import jax

    with _LOCK:
        if name in _TARGETS:
            return
        handler = _handler(name, fn)
        new_capsule = ctypes.pythonapi.PyCapsule_New
        new_capsule.restype, new_capsule.argtypes = ctypes.py_object, (ctypes.c_void_p, ctypes.c_char_p, ctypes.c_void_p)
        capsule = new_capsule(ctypes.cast(handler, ctypes.c_void_p).value, b"xla._CUSTOM_CALL_TARGET", None)
        jax.ffi.register_ffi_target(name, capsule, platform="cpu", api_version=1)
        _TARGETS[name] = (handler, capsule, fn)


def traced_calls() -> int:
    """How many host calls have been traced in this process: a program traced while it grew calls
    back into Python, and its executable is worth nothing without this process's registrations
    (:mod:`impls.jax.executables` stores no such program)."""
    return _CALLS[0]


def on_cpu() -> bool:
    """Whether jax's default backend is the CPU (then :func:`host_call` is a cacheable custom call)."""
    import jax

    return jax.default_backend() == "cpu"


def host_call(name: str, fn: Callable, x, out_shapes):
    """``fn(x)`` inside a jax program: ``fn`` takes and returns float64 numpy arrays; ``out_shapes``
    is a tuple of ``jax.ShapeDtypeStruct`` (the results, cast to their dtypes); returns a tuple of
    jax arrays.  ``name`` must identify ``fn``'s content (see the module).  Batched under vmap by
    broadcasting (``vmap_method="broadcast_all"``): ``fn`` must work on any leading shape."""
    import jax

    _CALLS[0] += 1
    if not on_cpu():
        def host(a):
            return tuple(np.asarray(v).astype(s.dtype) for v, s in zip(fn(np.asarray(a, np.float64)), out_shapes))

        return jax.pure_callback(host, tuple(out_shapes), x, vmap_method="broadcast_all")
    _register(name, fn)
    return tuple(jax.ffi.ffi_call(name, tuple(out_shapes), vmap_method="broadcast_all")(x))
