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

import functools
import hashlib
import inspect
import pickle
import types
from pathlib import Path
from typing import Any, Callable, NamedTuple

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


@functools.cache
def _installed_roots() -> tuple[str, ...]:
    """Where the interpreter's own and installed packages live (the standard library, site-packages)."""
    import sys
    import sysconfig

    roots = {sys.prefix, sys.base_prefix, *(sysconfig.get_paths().get(k, "") for k in ("stdlib", "purelib", "platlib"))}
    return tuple(str(Path(r).resolve()) for r in roots if r)


def _users_module(mod: types.ModuleType) -> bool:
    """Whether ``mod`` is a user's module (a file outside the standard library and site-packages;
    a module made at run time counts too): code that may change between runs, unlike numpy's."""
    path = getattr(mod, "__file__", None)
    if path is None:
        return getattr(mod, "__spec__", None) is None or getattr(mod.__spec__, "origin", None) is None
    try:
        resolved = str(Path(path).resolve())
    except OSError:
        return True
    return not resolved.startswith(_installed_roots())


class _ModuleAttr(NamedTuple):
    """An attribute a function reads from a user's module (``helpers.radius``), for its digest."""

    module: str
    name: str
    value: Any


def _value_digest(v: Any, depth: int = 0) -> bytes:
    """Bytes that change when a value a function closes over or defaults to changes."""
    if isinstance(v, np.ndarray):
        return repr((v.dtype.str, v.shape)).encode() + np.ascontiguousarray(v).tobytes()
    if isinstance(v, _ModuleAttr):
        return f"{v.module}.{v.name}=".encode() + _value_digest(v.value, depth)
    if callable(v) and depth < 4:
        return function_digest(v, depth + 1).encode()
    try:
        return pickle.dumps(v, protocol=5)
    except Exception:  # noqa: BLE001 - unpicklable (its class not importable by name, say)
        state = getattr(v, "__dict__", None)
        if isinstance(state, dict) and depth < 4:  # an instance: its class and its attributes' values
            parts = [f"{type(v).__module__}.{type(v).__qualname__}".encode()]
            parts += [k.encode() + _value_digest(x, depth + 1) for k, x in sorted(state.items())]
            return b"|".join(parts)
        return repr(v).encode()  # (an address in it makes the hash change every run: safe)


def function_digest(fn: Callable, depth: int = 0) -> str:
    """A digest of what a user's function ``fn`` computes, for a :class:`CallableField`'s content
    hash (``spec``): the bytes of the source file that defines it (a helper it calls may change
    there), its code (bytecode, names, constants), its defaults, what it closes over and the
    globals it reads by name (helper functions recursively; of a user's module, the attributes the
    code names; for a bound method, the instance); for a callable object, its class's file and its
    pickled state.  Two functions of the same ``name``
    that compute differently get different hashes, so a run's kept references (first hits,
    rendering integrals), ``--resume`` and ``bench compare`` never take one for the other.  A
    change of what it reads otherwise (an installed module's attribute, a file's contents) is not seen: give
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
        # the globals it reads by name (a module-level constant, a helper function), and of a user's
        # module it reads (``helpers.radius()``) the attributes its code names: a helper edited in
        # another file changes the digest (it kept the same one, and the kept reference answers of
        # the old field judged the new one)
        glb = getattr(func, "__globals__", {})
        names = _global_names(code)
        reads = [glb[n] for n in sorted(names) if n in glb and not isinstance(glb[n], types.ModuleType)]
        for n in sorted(names):
            mod = glb.get(n)
            if isinstance(mod, types.ModuleType) and _users_module(mod):
                reads += [_ModuleAttr(n, a, getattr(mod, a)) for a in sorted(names) if a in vars(mod)]
        # a bound method: the instance it is bound to (``Ball(r).phi`` reads its r through self)
        bound = getattr(fn, "__self__", None)
        if bound is not None and not isinstance(bound, types.ModuleType):
            reads.append(bound)
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
