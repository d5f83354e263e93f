"""What identifies a user's code in a scene's content hash (:meth:`reference.scene.Field.spec`):
a digest of what a function, callable object or class computes, stable across processes.

A scene's content hash keys the reference answers kept on disk (numerical first hits, rendering
integrals), ``--resume``'s changed-case check and ``bench compare``'s row matching.  The library's
own nodes are described by their parameters (their code is the package's, which those keys hold
by its source digest); a user's function or ``Field`` subclass is code the package cannot see
change, so its hash holds this digest of it.  Written here rather than taken from ``pickle`` or
``marshal``: a function pickles by reference (its name, not its body), and marshal's output
depends on reference counts, so neither is a content digest.
"""

from __future__ import annotations

import hashlib
import inspect
import pickle
import types
from pathlib import Path
from typing import Any, Callable

import numpy as np


def _code_parts(code: types.CodeType) -> tuple:
    """A code object's bytecode, names and constants (nested code objects recursively): what it
    computes, without marshal's output, which depends on reference counts (not stable across
    processes)."""
    consts = tuple(_code_parts(c) if isinstance(c, types.CodeType) else repr(c) for c in code.co_consts)
    return (code.co_code, consts, code.co_names, code.co_varnames, code.co_freevars, code.co_cellvars)


def _global_names(code: types.CodeType) -> set[str]:
    """The names a code object (and the code nested in it) may read as globals."""
    out = set(code.co_names)
    for c in code.co_consts:
        if isinstance(c, types.CodeType):
            out |= _global_names(c)
    return out


def _value_digest(v: Any, depth: int = 0) -> bytes:
    """Bytes that change when a value a function closes over or defaults to changes."""
    if isinstance(v, np.ndarray):
        return repr((v.dtype.str, v.shape)).encode() + np.ascontiguousarray(v).tobytes()
    if callable(v) and depth < 4:
        return function_digest(v, depth + 1).encode()
    try:
        return pickle.dumps(v, protocol=5)
    except Exception:  # noqa: BLE001 - unpicklable: its repr (an address in it makes the hash change every run: safe)
        return repr(v).encode()


def function_digest(fn: Callable, depth: int = 0) -> str:
    """A digest of what a user's function ``fn`` computes, for a :class:`CallableField`'s content
    hash (``spec``): the bytes of the source file that defines it (a helper it calls may change
    there), its code (bytecode, names, constants), its defaults, what it closes over and the
    globals it reads by name (helper functions recursively, modules aside); for a
    callable object, its class's file and its pickled state.  Two functions of the same ``name``
    that compute differently get different hashes, so a run's kept references (first hits,
    rendering integrals), ``--resume`` and ``bench compare`` never take one for the other.  A
    change of what it reads otherwise (a module's attribute, a file's contents) is not seen: give
    the field another ``name`` then.  Never raises; what it cannot read it leaves out."""
    h = hashlib.sha256()
    target = fn if isinstance(fn, (types.FunctionType, types.MethodType, type)) else type(fn)
    try:
        path = inspect.getsourcefile(target)
        if path:
            h.update(Path(path).read_bytes())
    except (TypeError, OSError):
        pass
    func = getattr(fn, "__func__", fn)
    code = getattr(func, "__code__", None)
    if code is not None:
        h.update(repr(_code_parts(code)).encode())
        cells = []
        for c in getattr(func, "__closure__", None) or ():
            try:
                cells.append(c.cell_contents)
            except ValueError:  # an empty cell
                cells.append(None)
        # the globals it reads by name (a module-level constant, a helper function), modules aside
        glb = getattr(func, "__globals__", {})
        reads = [glb[n] for n in sorted(_global_names(code)) if n in glb and not isinstance(glb[n], types.ModuleType)]
        for v in (*(getattr(func, "__defaults__", None) or ()), *cells,
                  *sorted((getattr(func, "__kwdefaults__", None) or {}).items()), *reads):
            h.update(_value_digest(v, depth))
    elif isinstance(fn, type):  # a class: its name and the code and values of what it defines
        h.update(f"{fn.__module__}.{fn.__qualname__}".encode())
        for key, v in sorted(vars(fn).items()):
            if key.startswith("__") and key not in ("__call__", "__init__"):
                continue
            v = getattr(v, "__func__", None) or getattr(v, "fget", None) or v  # static/class methods, properties
            if depth < 4:
                h.update(key.encode() + _value_digest(v, depth + 1))
    else:  # a callable object: its state
        try:
            h.update(pickle.dumps(fn, protocol=5))
        except Exception:  # noqa: BLE001 - unpicklable: its attributes' repr
            h.update(repr(getattr(fn, "__dict__", fn)).encode())
    return h.hexdigest()[:16]
