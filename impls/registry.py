"""Backend registry: ids ``lib[:device]``, lazy imports, plug-ins.

* Built-ins: ``numpy``, ``torch:cpu`` / ``torch:cuda[:N]``, ``jax:cpu`` / ``jax:gpu``.  A
  library is located with ``importlib.util.find_spec`` (no import) so listing is cheap, in the
  spirit of einops' ``_backends.py``; it is imported only when a backend is made.
* Plug-ins: entry points in the group ``isobench.backends`` (``name = "pkg.mod:factory"``), or
  a spec ``pkg.mod:attr`` passed as ``--backend``.  ``attr`` is a backend object, a class, or a
  factory taking ``device`` (or nothing) and returning a backend.
* An unavailable backend is never an error in a run: :func:`resolve` returns a
  :class:`Unavailable` with the reason, which the report lists as skipped.
"""

from __future__ import annotations

import dataclasses
import importlib
import importlib.metadata
import importlib.util
import inspect
from typing import Any

ENTRY_POINT_GROUP = "isobench.backends"

# lib -> (module that must be importable, factory "module:attr")
_BUILTIN = {
    "numpy": ("numpy", "impls.numpy.backend:NumpyBackend"),
    "torch": ("torch", "impls.torch.backend:TorchBackend"),
    "jax": ("jax", "impls.jax.backend:JaxBackend"),
}
_DEFAULT_DEVICE = {"numpy": "cpu", "torch": "cpu", "jax": "cpu"}


@dataclasses.dataclass(frozen=True)
class Unavailable:
    id: str
    reason: str


def _load_attr(spec: str) -> Any:
    if ":" not in spec:
        raise ValueError(f"backend spec {spec!r} must look like 'package.module:attr'")
    mod, attr = spec.split(":", 1)
    obj = importlib.import_module(mod)
    for part in attr.split("."):
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


def _is_plugin_spec(backend_id: str) -> bool:
    # "pkg.mod:attr" has a dot before the colon; "torch:cuda" does not.
    head = backend_id.split(":", 1)[0]
    return ":" in backend_id and "." in head


def resolve(backend_id: str) -> Any:
    """A backend object for ``backend_id``, or :class:`Unavailable` with the reason."""
    if _is_plugin_spec(backend_id):
        try:
            return _instantiate(_load_attr(backend_id), None)
        except Exception as exc:  # a broken plug-in is reported, never fatal
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
            return _instantiate(eps[lib].load(), device or None)
        except Exception as exc:
            return Unavailable(backend_id, f"entry point {lib!r} failed: {type(exc).__name__}: {exc}")
    known = sorted(set(_BUILTIN) | set(eps))
    return Unavailable(backend_id, f"unknown backend {backend_id!r}; known: {known} or 'package.module:attr'")


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
