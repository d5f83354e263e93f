"""Backend registry: ids ``lib[:device]``, lazy imports, plug-ins.

* Built-ins: ``numpy``, ``torch:cpu`` / ``torch:cuda[:N]``, ``jax:cpu`` / ``jax:gpu``.  A
  library is located with ``importlib.util.find_spec`` (no import) so listing is cheap, in the
  spirit of einops' ``_backends.py``; it is imported only when a backend is made.
* Plug-ins: entry points in the group ``isobench.backends`` (``name = "pkg.mod:factory"``), or
  a spec ``module:attr`` passed as ``--backend`` (``module`` dotted or not: any id with a colon
  whose head is neither a built-in library nor an entry point).  ``attr`` is a backend object, a
  class, or a factory taking ``device`` (or nothing) and returning a backend.
* An unavailable backend is never an error in a run: :func:`resolve` returns a
  :class:`Unavailable` with the reason, which the report lists as skipped.  An id that names
  nothing (a typo: no such built-in or entry point, a spec whose module or attribute does not
  exist) is an :class:`Unavailable` with ``unknown=True``, which the CLI refuses as a usage error.
* A plug-in's own ``id`` names it everywhere (rows, reports, ``bench compare``, file names of its
  records), so it must be a backend id (:func:`id_problem`: letters, digits and ``_.:+-``); one
  that is not makes the plug-in an :class:`Unavailable` saying so, never a row under that name.
"""

from __future__ import annotations

import dataclasses
import importlib
import importlib.metadata
import importlib.util
import inspect
import re
from typing import Any

ENTRY_POINT_GROUP = "isobench.backends"

# lib -> (module that must be importable, factory "module:attr")
_BUILTIN = {
    "numpy": ("numpy", "impls.numpy.backend:NumpyBackend"),
    "torch": ("torch", "impls.torch.backend:TorchBackend"),
    "jax": ("jax", "impls.jax.backend:JaxBackend"),
}
_DEFAULT_DEVICE = {"numpy": "cpu", "torch": "cpu", "jax": "cpu"}


#: a backend id: letters, digits and ``_.:+-`` (``numpy``, ``torch:cuda:0``, ``mitsuba:llvm``), so
#: that it reads the same in a report's Markdown and HTML, a file name and a shell, and cannot split
#: a table cell (``|``) or carry markup (``<``)
ID_PATTERN = re.compile(r"[A-Za-z0-9_.:+\-]+")


def id_problem(backend_id: Any) -> str | None:
    """What makes ``backend_id`` (a backend's ``id``) unfit to name it (:data:`ID_PATTERN`), as a
    phrase naming the id (its other characters escaped, so the message is safe to print anywhere),
    or None when it is fine."""
    if not isinstance(backend_id, str):
        return f"its id is not a string but {type(backend_id).__name__}"
    if not backend_id:
        return "its id is empty"
    if ID_PATTERN.fullmatch(backend_id):
        return None
    shown = "".join(c if ID_PATTERN.fullmatch(c) else f"\\u{ord(c):04x}" for c in backend_id[:80])
    shown += "…" if len(backend_id) > 80 else ""
    return f"its id '{shown}' holds characters other than letters, digits and _.:+-"


@dataclasses.dataclass(frozen=True)
class Unavailable:
    """A backend that cannot run here, and why.  ``unknown``: the id names no backend at all (no
    such built-in or entry point; a plug-in spec whose module or attribute does not exist), as
    opposed to one that exists but cannot load (a library not installed, a factory that raises)."""

    id: str
    reason: str
    unknown: bool = False


class _NotFound(LookupError):
    """A plug-in spec names a module or attribute that does not exist."""


def _checked_plugin(obj: Any, spec: str, own: str | None = None) -> Any:
    """The plug-in ``obj`` (resolved from ``spec``; ``own``: the entry point's name it was loaded
    by), or an :class:`Unavailable` naming its ``id`` and the fix when that is no backend id
    (:func:`id_problem`) or names another backend: a built-in's library (``numpy``, ``torch``,
    ``jax``) or another installed entry point.  (A plug-in called ``torch:cpu`` in a run without
    torch had its rows reported, compared and baselined as torch's.)"""
    try:
        bid = getattr(obj, "id", None)
        problem = id_problem(bid)
        # read again: every later use reads it anew, and an id that changes between reads passed
        # this check as one name and ran (and was reported) as a built-in's
        if problem is None and any(getattr(obj, "id", None) != bid for _ in range(2)):
            problem = f"its id {bid!r} changes from one read to the next (make `id` a plain attribute)"
        if problem is None:
            lib = bid.partition(":")[0]
            eps = _entry_points()
            # (the entry point's own target named as a spec is that backend, not another)
            if lib in _BUILTIN or (lib != own and lib in eps and eps[lib].value != spec):
                problem = (f"its id {bid!r} names the backend {lib!r} (built-in or installed), whose rows it would pass "
                           "for")
    except Exception as exc:  # noqa: BLE001 - a property of a user's class: whatever it raises
        problem = f"reading its id raised {type(exc).__name__}: {exc}"
    if problem is None:
        return obj
    return Unavailable(spec, f"{spec}: {problem}; set the backend's `id` attribute to a name of letters, digits and "
                             "_.:+- (e.g. 'mine' or 'mylib:cuda'): it names the backend in rows, reports and --backend")


def _no_module(name: str, spec: str) -> str:
    return f"no module named {name!r} (from backend spec {spec!r}); is it installed or on PYTHONPATH?"


def _unknown(backend_id: str, eps) -> str:
    return f"unknown backend {backend_id!r}; known: {sorted(set(_BUILTIN) | set(eps))} or 'package.module:attr'"


def _load_attr(spec: str) -> Any:
    """The object ``module:attr`` names; :class:`_NotFound` when the module or an attribute on the
    way does not exist (errors raised *inside* an existing module propagate as they are)."""
    mod, _, attr = spec.partition(":")
    if not mod or not attr or not all(p.isidentifier() for p in mod.split(".") + attr.split(".")):
        raise _NotFound(f"backend spec {spec!r} must look like 'module:attr' (e.g. 'mypkg.backend:MyBackend')")
    try:
        obj = importlib.import_module(mod)
    except ModuleNotFoundError as exc:
        if exc.name and (mod == exc.name or mod.startswith(exc.name + ".")):
            raise _NotFound(_no_module(exc.name, spec)) from None
        raise
    for part in attr.split("."):
        if not hasattr(obj, part):
            raise _NotFound(f"{mod}:{attr}: {getattr(obj, '__name__', mod)!r} has no attribute {part!r}")
        obj = getattr(obj, part)
    return obj


def _instantiate(obj: Any, device: str | None) -> Any:
    if not callable(obj) or hasattr(obj, "prepare") and not inspect.isclass(obj):
        return obj
    params = inspect.signature(obj).parameters
    if device is not None and "device" in params:
        return obj(device=device)
    return obj()


def _entry_points() -> dict[str, importlib.metadata.EntryPoint]:
    return {ep.name: ep for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)}


def is_plugin_spec(backend_id: str, entry_points=None) -> bool:
    # "pkg.mod:attr" or "mod:attr"; "torch:cuda" (a built-in) and "<entry point>:device" are not
    head = backend_id.split(":", 1)[0]
    if ":" not in backend_id or head in _BUILTIN:
        return False
    return "." in head or head not in (_entry_points() if entry_points is None else entry_points)


def resolve(backend_id: str) -> Any:
    """A backend object for ``backend_id``, or :class:`Unavailable` with the reason."""
    if not isinstance(backend_id, str) or not backend_id.strip():
        return Unavailable(str(backend_id), "empty backend id; use e.g. 'numpy', 'torch:cpu' or 'package.module:attr'",
                           unknown=True)
    if is_plugin_spec(backend_id):
        try:
            return _checked_plugin(_instantiate(_load_attr(backend_id), None), backend_id)
        except _NotFound as exc:
            return Unavailable(backend_id, f"could not load {backend_id}: {exc}", unknown=True)
        except (Exception, SystemExit) as exc:  # a broken plug-in is reported, never fatal
            return Unavailable(backend_id, f"could not load {backend_id}: {type(exc).__name__}: {exc}")
    lib, _, device = backend_id.partition(":")
    if lib in _BUILTIN:
        module, factory = _BUILTIN[lib]
        if importlib.util.find_spec(module) is None:
            return Unavailable(backend_id, f"{module} is not installed (pip install -c constraints.txt -e '.[{lib}]')")
        try:
            cls = _load_attr(factory)
            return cls(device=device or _DEFAULT_DEVICE[lib])
        except Exception as exc:
            return Unavailable(backend_id, f"{type(exc).__name__}: {exc}")
    eps = _entry_points()
    if lib in eps:
        try:
            return _checked_plugin(_instantiate(eps[lib].load(), device or None), backend_id, own=lib)
        except (Exception, SystemExit) as exc:
            return Unavailable(backend_id, f"entry point {lib!r} failed: {type(exc).__name__}: {exc}")
    return Unavailable(backend_id, _unknown(backend_id, eps), unknown=True)


def unknown_reason(backend_id: str) -> str | None:
    """Why ``backend_id`` names no backend, found without building one or importing its library
    (a built-in's name, an installed entry point, a plug-in spec whose module can be found), or
    None; :func:`resolve` says more (a plug-in's missing attribute, a library that fails)."""
    if not isinstance(backend_id, str) or not backend_id.strip():
        return "empty backend id; use e.g. 'numpy', 'torch:cpu' or 'package.module:attr'"
    if is_plugin_spec(backend_id):
        module = backend_id.split(":", 1)[0]
        if not all(p.isidentifier() for p in module.split(".")):
            return None  # resolve() names what is wrong with the spec's form
        try:
            missing = None if importlib.util.find_spec(module) is not None else module
        except ModuleNotFoundError as exc:  # a parent package that does not exist
            missing = exc.name or module
        except (ImportError, ValueError):  # something else: resolve() says it
            return None
        return f"could not load {backend_id}: {_no_module(missing, backend_id)}" if missing else None
    lib = backend_id.partition(":")[0]
    if lib in _BUILTIN:
        return None
    eps = _entry_points()
    return None if lib in eps else _unknown(backend_id, eps)


def default_ids() -> list[str]:
    """The ids a run uses when none are given: every built-in on CPU, accelerators when present,
    and every installed entry point."""
    ids = ["numpy", "torch:cpu", "jax:cpu"]
    if importlib.util.find_spec("torch") is not None:
        try:
            import torch

            if torch.cuda.is_available():
                ids.append("torch:cuda")
        except Exception:  # pragma: no cover - broken install is reported by resolve()
            pass
    if importlib.util.find_spec("jax") is not None:
        try:
            import jax

            if any(d.platform == "gpu" for d in jax.devices()):
                ids.append("jax:gpu")
        except Exception:  # pragma: no cover
            pass
    ids.extend(sorted(_entry_points()))
    return ids


def available(ids: list[str] | None = None) -> tuple[list[Any], list[Unavailable]]:
    """Split ``ids`` (default: :func:`default_ids`) into backends and unavailable ones."""
    ok, missing = [], []
    for bid in ids or default_ids():
        b = resolve(bid)
        (missing if isinstance(b, Unavailable) else ok).append(b)
    return ok, missing
