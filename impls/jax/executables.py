"""Compiled jax kernels kept on disk by what they compute, so that a warm run neither traces nor
lowers them.

jax's persistent compilation cache (``<cache dir>/jax``, :mod:`impls.jax.backend`) is keyed by
the lowered program, so a warm run still traces and lowers every kernel to find its entry: 14 of
the 20 CPU-seconds a warm quick run spent getting its 163 jax kernels (measured: trace 7.7 s,
lower 6.4 s, loading the executables 5.8 s).  This store keys a kernel instead by everything it
is a function of, computed without tracing (:func:`kernel_key`), and keeps the executable
(``jax.experimental.serialize_executable``) under ``<cache dir>/jax-kernels/<key>.bin``.

What the key holds, and why it is complete:

* the kernel's inputs as :meth:`JaxBackend.compile_configuration` keys its in-process table:
  the method, the depth range, the knobs compiled in and the names and types of the traced ones,
  the device, the driver settings, the rays' shapes and dtypes;
* the scene and colour objects *by value*: their pickle, in which every class, function and
  global must come from isobench's own packages (``reference``, ``impls``), numpy or Python's
  builtins (:func:`value_digest`).  A user's scene class or function (code this store cannot
  see change) gives no key, and the kernel is traced as before;
* the code: the SHA-256 of every ``.py`` file of the ``impls`` and ``reference`` packages (the
  methods, drivers and fields that are traced), and the method's implementation and the backend's
  class must come from them;
* the libraries and the machine: jax, jaxlib, numpy and Python versions, every ``jax.config``
  value, ``XLA_FLAGS``, the device's platform and kind, and the CPU's model and feature flags
  (XLA compiles for the host's instruction set).

What is stored: a kernel XLA compiled in this process, whose serialization, loaded back, runs on
the configuration's arrays to the very same outputs (:meth:`KernelStore.save`).  That check runs
where it costs least: for a configuration whose inputs and outputs are small
(:data:`EXAMPLE_BYTES`) the entry carries them and the check runs at the entry's first load, on the
executable loaded anyway (a failed check removes the entry and refuses the key; a passed one
leaves a marker, and later loads check nothing more); for a larger one it runs before the entry
is written.  Loading an executable back only to check it was a cold run's cost for a load that a
warm run makes anyway (docs/performance.md).  The entry is written at the kernel's first call
(:class:`impls.jax.backend._SavedAtFirstCall`), from that call's arguments and outputs: the
outputs the check compares with are ones the run computed anyway.  Not stored:

* a kernel jax loaded from its persistent cache, where the bytes jax read are not at hand: such an
  executable serializes into bytes that do not run (jax 0.10.2 on the CPU, measured:
  ``NOT_FOUND: Function is-finite_reduce_fusion.1 not found``).  Where they are
  (:func:`persistent_cache_reads`), the entry is made of the bytes jax's cache held
  (:func:`serialize`), checked as any other: a kernel whose program is unchanged since jax cached
  it (after an edit of isobench elsewhere changed every key of this store) is stored at its first
  warm run, not traced and lowered on every run after it;
* a program that calls back into Python (jax's own cache does not keep one either): the meshes'
  φ is a custom call whose target is registered when it is traced
  (:mod:`reference.jax_host_call`), so skipping its trace would leave the target unregistered.

A store entry that cannot be read or loaded is removed and is a miss (the kernel is traced and
compiled, and stored again if XLA compiled it); entries are written atomically.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import io
import os
import pickle
import platform
import secrets
import sys
import threading
from pathlib import Path
from typing import Any

from ..cache import source_digest

#: bump when the entry format or the key's composition changes
FORMAT = 2

#: inputs plus outputs (bytes) up to which an entry carries its configuration's arrays and is
#: checked at its first load, not before it is written (:meth:`KernelStore.save`): 1,024 rays in
#: float64 with their per-ray outputs are ~0.1 MB
EXAMPLE_BYTES = 4 << 20

#: the store's size (bytes of its entries) past which a save removes the least recently used
#: entries (:meth:`KernelStore.prune`).  Every edit of ``impls/`` or ``reference/`` changes every
#: key, and a warm run stores its kernels anew under the new ones (a quick run's timed kernels and
#: the tests' untimed ones are ~0.3 GB each), so without a bound the store grows by that much per
#: edit; 2 GiB keeps the last few versions of the code
MAX_BYTES = 2 << 30
#: what a prune leaves, as a share of :data:`MAX_BYTES` (so that it does not run at every save)
PRUNE_TO = 0.75
#: bytes a store object writes between two looks at the store's size (a look reads every entry's
#: size: ~15 ms for 2,000 entries, once per save in a cold run of ~120 kernels was 1.6 s)
PRUNE_EVERY = 128 << 20

#: top-level packages whose classes, functions and globals may appear in a scene's pickle
_OWN = ("reference", "impls")
_TRUSTED = _OWN + ("numpy", "builtins", "copyreg", "_codecs", "collections")


class _Untrusted(Exception):
    pass


_reads = threading.local()


@functools.lru_cache(maxsize=1)
def _capture_installed() -> bool:
    """Wrap jax's reading of a persistent cache entry (``jax._src.compilation_cache``, whose
    ``get_executable_and_time`` calls ``extract_executable_and_time`` for the serialized executable)
    so that :func:`persistent_cache_reads` sees the bytes.  Returns whether it could (a jax without
    that function: such kernels are not stored, as before)."""
    try:
        from jax._src import compilation_cache
    except ImportError:  # pragma: no cover - a jax without the module
        return False
    extract = getattr(compilation_cache, "extract_executable_and_time", None)
    if extract is None:  # pragma: no cover - a jax without the function
        return False

    def capturing(executable_and_time):
        serialized, compile_time = extract(executable_and_time)
        reads = getattr(_reads, "bytes", None)
        if reads is not None:
            reads.append(serialized)
        return serialized, compile_time

    compilation_cache.extract_executable_and_time = capturing
    return True


@contextlib.contextmanager
def persistent_cache_reads():
    """A list of the serialized executables jax reads from its persistent cache in this thread
    while the context is open (empty where it read none, or where the reads cannot be seen)."""
    _capture_installed()
    before, _reads.bytes = getattr(_reads, "bytes", None), []
    try:
        yield _reads.bytes
    finally:
        _reads.bytes = before


def serialize(compiled, executable_bytes: bytes | None = None) -> tuple:
    """``jax.experimental.serialize_executable.serialize(compiled)``: ``(bytes, in_tree,
    out_tree)``; with ``executable_bytes``, the XLA executable in it is those bytes (what jax's
    persistent cache held for it, :func:`persistent_cache_reads`) instead of its own serialization,
    which does not run for an executable loaded from that cache.  The parts are jax's own
    (``serialize``'s body, jax 0.10.2): only the executable's pickled form differs."""
    import jax
    from jax.experimental import serialize_executable

    if executable_bytes is None:
        return serialize_executable.serialize(compiled)

    class Pickler(serialize_executable._JaxPjrtPickler):
        def persistent_id(self, obj):
            if isinstance(obj, (serialize_executable.xc.LoadedExecutable, serialize_executable._jax.Executable)):
                return ("exec", executable_bytes)
            return super().persistent_id(obj)

    unloaded = getattr(compiled._executable, "_unloaded_executable", None)
    if (unloaded is None or compiled._params.const_args
            or (getattr(unloaded, "mut", None) and unloaded.mut.in_mut)):
        raise ValueError("this compilation does not serialize")  # (where jax's own serialize refuses)
    args_info_flat, in_tree = jax.tree_util.tree_flatten(compiled.args_info)
    with io.BytesIO() as file:
        Pickler(file).dump((unloaded, args_info_flat, compiled._no_kwargs))
        return file.getvalue(), in_tree, compiled.out_tree


class _CheckingPickler(pickle.Pickler):
    """A pickler that refuses any object whose class (or, for a class or function, itself) comes
    from a module outside :data:`_TRUSTED`: its code is not in the store's key."""

    def reducer_override(self, obj):
        for thing in (obj, type(obj)) if isinstance(obj, type) or callable(obj) else (type(obj),):
            module = getattr(thing, "__module__", None) or ""
            if module.split(".")[0] not in _TRUSTED:
                raise _Untrusted(f"{thing!r} from module {module!r}")
        return NotImplemented


def value_digest(obj: Any) -> str | None:
    """SHA-256 of ``obj``'s pickle, or None where it cannot be pickled or holds anything from
    outside isobench's packages, numpy and the builtins (see :class:`_CheckingPickler`)."""
    buf = io.BytesIO()
    try:
        _CheckingPickler(buf, protocol=5).dump(obj)
    except Exception:  # noqa: BLE001 - unpicklable or untrusted: no key, the kernel is traced
        return None
    return hashlib.sha256(buf.getvalue()).hexdigest()


@functools.lru_cache(maxsize=1)
def _cpu_flags() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            lines = [ln for ln in f if ln.startswith(("model name", "flags"))]
        return "".join(sorted(set(lines)))
    except OSError:
        return platform.processor()


def _environment(device) -> str:
    import jax
    import jaxlib
    import numpy as np

    config = sorted((k, repr(v)) for k, v in jax.config.values.items())
    return repr((FORMAT, sys.version, jax.__version__, jaxlib.__version__, np.__version__, config,
                 os.environ.get("XLA_FLAGS", ""), device.platform, device.device_kind, platform.machine(), _cpu_flags()))


def array_layout(a: Any):
    """What a kernel is compiled for of an input: None, an array's ``(shape, dtype)``, or a dict
    of arrays' ``((key, layout), …)`` in key order (a shading kernel's input hit)."""
    if a is None:
        return None
    if isinstance(a, dict):
        return tuple((k, array_layout(v)) for k, v in sorted(a.items()))
    return (tuple(a.shape), str(a.dtype))


def _own(obj: Any) -> bool:
    return (getattr(obj, "__module__", None) or "").split(".")[0] in _OWN


def kernel_key(backend, method: str, scene, t_range, extra: dict, static: dict, traced: dict, arrays,
               impl=None) -> str | None:
    """The store's key of a kernel of :meth:`JaxBackend.compile_configuration` (hex SHA-256), or
    None where the kernel depends on code outside isobench's packages (a user's scene, colour
    field, method or backend class) and must be traced.  ``impl``: the function the kernel runs
    where it is not ``method``'s implementation (a part of one: a volume renderer's sampler)."""
    impl = impl if impl is not None else getattr(backend, "_impl", {}).get(method)
    if impl is None or not _own(impl) or not _own(type(backend)):
        return None
    values = value_digest((scene, extra))
    if values is None:
        return None
    parts = (_environment(backend.jax_device), source_digest(*_OWN), values, method, t_range,
             sorted((k, repr(v)) for k, v in static.items()),
             sorted((k, type(v).__name__) for k, v in traced.items()), backend.device, repr(backend.settings),
             [array_layout(a) for a in arrays])
    return hashlib.sha256(repr(parts).encode()).hexdigest()


class KernelStore:
    """Executables under ``root`` by :func:`kernel_key`, at most ``max_bytes`` of them (the least
    recently used go first: :meth:`prune`)."""

    def __init__(self, root: Path, max_bytes: int = MAX_BYTES):
        self.root = Path(root)
        self.max_bytes = max_bytes
        self._unpruned = PRUNE_EVERY  # bytes written since the last prune: the first save looks

    def prune(self) -> int:
        """Remove the least recently used entries (a load marks its entry used: its modification
        time) while the entries take more than ``max_bytes``, down to :data:`PRUNE_TO` of it; an
        entry's ``.checked`` marker goes with it (``.refused`` markers stay: empty files that keep
        a failed key from being stored again).  Returns the bytes removed.  Another process
        removing or writing entries meanwhile costs nothing but a miss."""
        entries = []
        try:
            with os.scandir(self.root) as it:
                for e in it:
                    if e.name.endswith(".bin"):
                        try:
                            st = e.stat()
                        except OSError:
                            continue
                        entries.append((st.st_mtime, st.st_size, e.name))
        except OSError:
            return 0
        total = sum(size for _, size, _ in entries)
        if total <= self.max_bytes:
            return 0
        removed = 0
        for _, size, name in sorted(entries):
            if total - removed <= PRUNE_TO * self.max_bytes:
                break
            _unlink(self.root / name)
            _unlink(self._checked(name[: -len(".bin")]))
            removed += size
        return removed

    def _path(self, key: str) -> Path:
        return self.root / f"{key}.bin"

    def _refused(self, key: str) -> Path:
        return self.root / f"{key}.refused"

    def _checked(self, key: str) -> Path:
        return self.root / f"{key}.checked"

    def refuses(self, key: str) -> bool:
        """Whether ``key`` is refused (its entry once failed its check): :meth:`save` stores it no more."""
        return self._refused(key).exists()

    def load(self, key: str, device):
        """The executable stored under ``key``, loaded onto ``device``, or None (absent, or an
        entry that cannot be read or loaded: removed, a miss).  An entry that carries its
        configuration's arrays (:meth:`save`) is run on them at its first load: outputs other than
        the stored ones, bit for bit, remove it and refuse the key (a marker file ``<key>.refused``:
        :meth:`save` stores it no more); the same outputs leave a marker ``<key>.checked``, and
        later loads run nothing more (a marker, not a rewrite of the entry: the executables are
        large)."""
        from jax.experimental import serialize_executable

        path = self._path(key)
        try:
            with open(path, "rb") as f:
                entry = pickle.load(f)
            loaded = serialize_executable.deserialize_and_load(*entry["parts"], execution_devices=[device])
        except FileNotFoundError:
            return None
        except Exception:  # noqa: BLE001 - a damaged or foreign entry: removed, a miss
            _unlink(path)
            _unlink(self._checked(key))
            return None
        try:
            os.utime(path)  # used now: the last to go when the store is pruned
        except OSError:
            pass
        if entry.get("example") is None or self._checked(key).exists():
            return loaded
        args, want = entry["example"]
        try:
            same = _same_outputs(want, loaded(*args))
        except Exception:  # noqa: BLE001 - an executable that does not run: as one that runs wrong
            same = False
        try:
            if not same:
                _unlink(path)
                _write_atomically(self._refused(key), b"")
                return None
            _write_atomically(self._checked(key), b"")
        except OSError:  # a read-only or full cache directory: the check stands, the entry stays as it was
            pass
        return loaded if same else None

    def save(self, key: str, compiled, example_args: tuple, device, outputs=None,
             executable_bytes: bytes | None = None) -> bool:
        """Write ``compiled`` under ``key`` atomically (a temporary file renamed onto the entry),
        once its serialization is known to run as ``compiled`` does on ``example_args`` (bit for
        bit, NaN where NaN): with those arrays and ``compiled``'s outputs carried in the entry, to
        be checked at its first load (:meth:`load`), where they take at most
        :data:`EXAMPLE_BYTES`; else checked here, the serialization loaded back and run.  A key
        whose check failed before (its marker) is not stored.  ``outputs``: what ``compiled``
        returned for ``example_args`` (given by a caller that ran it anyway; else it is run here).
        ``executable_bytes``: the serialized executable jax's persistent cache held for
        ``compiled`` (:func:`serialize`), for a kernel loaded from there.  Returns whether it was
        stored; a failure to serialize, check or write leaves no entry and is not an error."""
        import jax
        import numpy as np
        from jax.experimental import serialize_executable

        if self.refuses(key):
            return False
        try:
            parts = serialize(compiled, executable_bytes)
            want = [np.asarray(a) for a in jax.tree.leaves(compiled(*example_args) if outputs is None else outputs)]
            args = jax.tree.map(lambda a: np.asarray(a) if isinstance(a, jax.Array) else a, example_args)
            size = sum(a.nbytes for a in want) + sum(np.asarray(a).nbytes for a in jax.tree.leaves(args))
            if size <= EXAMPLE_BYTES:
                entry = {"parts": parts, "example": (args, want)}
            else:
                again = serialize_executable.deserialize_and_load(*parts, execution_devices=[device])
                if not _same_outputs(want, again(*example_args)):
                    return False
                entry = {"parts": parts, "example": None}
            blob = pickle.dumps(entry, protocol=5)
            self.root.mkdir(parents=True, exist_ok=True)
            _unlink(self._checked(key))  # (a marker left by an entry this one replaces)
            _write_atomically(self._path(key), blob)
            self._unpruned += len(blob)
            if self._unpruned >= PRUNE_EVERY:
                self._unpruned = 0
                self.prune()
            return True
        except Exception:  # noqa: BLE001 - an unserializable executable or a full disk: not stored
            return False


def _same_outputs(want: list, outputs) -> bool:
    """Whether ``outputs`` (a pytree of arrays) are ``want`` (their leaves), bit for bit up to NaN."""
    import jax
    import numpy as np

    got = jax.tree.leaves(outputs)
    return len(want) == len(got) and all(np.array_equal(a, np.asarray(b), equal_nan=True) for a, b in zip(want, got))


def _unlink(path: Path) -> None:
    try:
        path.unlink()
    except OSError:
        pass


def _write_atomically(path: Path, blob: bytes) -> None:
    """``blob`` as the file ``path``: a temporary file beside it renamed onto it (a process beside
    this one reads a whole entry or none); a temporary file left by a failure is removed."""
    tmp = path.parent / f".{path.name}.{secrets.token_hex(4)}.tmp"
    try:
        with open(tmp, "wb") as f:
            f.write(blob)
        os.replace(tmp, path)
    finally:
        _unlink(tmp)


def default_store() -> KernelStore | None:
    """The store of the bench commands' cache directory (``<cache dir>/jax-kernels``), or None
    without one (:mod:`impls.cache`)."""
    from ..cache import subdir

    where = subdir("jax-kernels")
    return None if where is None else KernelStore(where)
