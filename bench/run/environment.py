"""The environment a run records: machine, threads, library versions, commit."""

from __future__ import annotations

import json
import os
import platform
import subprocess
from importlib import metadata
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]  # the repository (bench/run/environment.py)
LIBS = ["numpy", "scipy", "torch", "jax", "jaxlib", "pandas", "pyarrow", "matplotlib", "array-api-compat",
        "trimesh", "libigl", "scikit-image", "mpmath"]


def _git_commit() -> str:
    try:
        out = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], cwd=ROOT, capture_output=True, text=True, timeout=10)
        commit = out.stdout.strip() or "unknown"
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                               capture_output=True, text=True, timeout=10).stdout.strip()
        return commit + ("-dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS")
RECORDED_VARS = THREAD_VARS + ("OMP_WAIT_POLICY", "XLA_FLAGS")


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/isobench``, else ``~/.cache/isobench`` (the XDG base directory rule)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "isobench"


def configure_caches(cache_dir: Path | None) -> dict[str, str]:
    """Persistent caches between runs, all under one directory, set up *before* any backend is
    imported: ``jax/`` (jax's persistent compilation cache, :mod:`impls.jax.backend`), ``numba/``
    (numba's on-disk cache and the generated kernel modules, :mod:`impls.numba.driver`) and
    ``reference/`` (costly reference answers, :mod:`bench.run.references`).  ``None`` (``--no-cache``):
    none of them is read or written, every kernel is compiled afresh.  Returns the record for
    environment.json (``cache_dir``)."""
    from impls.cache import CACHE_ENV
    if cache_dir is None:
        os.environ[CACHE_ENV] = ""
        return {"cache_dir": "none (--no-cache)"}
    cache_dir = Path(cache_dir).expanduser().resolve()
    cache_dir.mkdir(parents=True, exist_ok=True)
    os.environ[CACHE_ENV] = str(cache_dir)
    return {"cache_dir": str(cache_dir)}


def configure_driver(backend, threads: int) -> None:
    """Give a backend's loop driver ``threads`` worker threads where its settings have them
    (``backend.settings``: the numpy/torch compacting driver; jax's masked driver has none, XLA
    is configured by :func:`configure_threads`).  A plug-in without settings is left alone."""
    settings = getattr(backend, "settings", None)
    configure = getattr(backend, "configure", None)
    if callable(configure) and "threads" in getattr(type(settings), "__dataclass_fields__", {}):
        configure(threads=threads)


def untimed_backend(backend):
    """``backend`` as a run that times nothing uses it (``TimingPolicy.accuracy_only``: the stability
    stage, ``--accuracy-only``): a copy configured with the driver settings its optional hook
    ``untimed_settings() -> dict`` names, settings that give the same per-ray results at less
    compile cost (jax: one compaction level, :meth:`impls.jax.backend.JaxBackend.untimed_settings`;
    numba: no per-ray marcher kernels, :meth:`impls.numba.backend.NumbaBackend.untimed_settings`),
    recorded with every row as any settings are.  The backend itself where it has no such hook,
    or where the hook or the settings it names fail: a plug-in's fault costs it the saving, not
    its rows."""
    import copy

    hook = getattr(backend, "untimed_settings", None)
    if not callable(hook) or not callable(getattr(backend, "configure", None)):
        return backend
    try:
        changes = hook()
        if not isinstance(changes, dict) or not changes:
            return backend
        twin = copy.copy(backend)  # the caller's object keeps its settings (a later timed run uses them)
        twin.configure(**changes)
        return twin
    except Exception:  # noqa: BLE001 - untrusted plug-in code
        return backend


def driver_record(backend) -> str:
    """``backend.settings.record()`` as JSON (the loop driver's settings, recorded with every row);
    "" for a backend that states none, or whose record fails (a plug-in's fault is not the run's)."""
    from . import interrupts

    try:
        settings = getattr(backend, "settings", None)
        if settings is None or not callable(getattr(settings, "record", None)):
            return ""
        return json.dumps(settings.record(), sort_keys=True)
    except BaseException as exc:  # noqa: BLE001 - untrusted plug-in code (its own KeyboardInterrupt too)
        if not interrupts.is_fault(exc):
            raise
        return ""


def configure_threads(n: int) -> dict[str, str]:
    """Fix the thread count of every library *before* it is imported, so timings are comparable
    across backends and runs: the BLAS/OpenMP variables, XLA's CPU thread pool and, once torch is
    imported, ``torch.set_num_threads``.  Variables the user already set are left alone (theirs
    wins, and is recorded).  Returns what was set."""
    if n < 1:
        raise ValueError(f"--threads must be ≥ 1, got {n}")
    done = {}
    for var in THREAD_VARS:
        if not os.environ.get(var):
            os.environ[var] = done[var] = str(n)
    if not os.environ.get("OMP_WAIT_POLICY"):
        # OpenMP threads that wait for work sleep instead of spinning.  torch's intra-op pool
        # (and OpenMP BLAS) spin at every parallel region's barrier by default; with more than
        # one thread on a machine whose cores are busy, a spinning thread holds the core its
        # partner needs, so adding threads makes a configuration slower instead of faster
        # (CHANGELOG.md, "torch under load").  Passive waiting costs a wake-up per region.
        os.environ["OMP_WAIT_POLICY"] = done["OMP_WAIT_POLICY"] = "PASSIVE"
    if "xla_cpu_multi_thread_eigen" not in os.environ.get("XLA_FLAGS", "") and n == 1:
        # XLA's CPU client spreads element-wise work over its Eigen thread pool; off = one thread
        flags = (os.environ.get("XLA_FLAGS", "") + " --xla_cpu_multi_thread_eigen=false").strip()
        os.environ["XLA_FLAGS"] = done["XLA_FLAGS"] = flags
    return done


# glibc mallopt parameters (malloc.h) and the values tune_allocator sets
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_MMAP_THRESHOLD, _TRIM_THRESHOLD = 1 << 30, (1 << 31) - 1
_allocator = "default"


def tune_allocator() -> str:
    """Keep freed array memory in the process: glibc ``mallopt`` with ``M_MMAP_THRESHOLD`` = 1 GiB
    (allocations below it come from the heap, not from a fresh ``mmap``) and
    ``M_TRIM_THRESHOLD`` = 2 GiB (freed heap memory is not handed back).

    Why: the numpy and torch drivers allocate temporaries of 2^16 float64 (512 KiB) on every
    array operation.  glibc serves such sizes by ``mmap`` until its dynamic threshold adapts,
    and trims the heap on free, so fresh pages keep being faulted in, and the page faults are
    timed with the method (the allocation-free time unit does not see them).  Transparent huge
    pages for torch (``THP_MEM_ALLOC_ENABLE=1``) address the same cost.  Setting only one of
    ``MALLOC_TRIM_THRESHOLD_``/``MALLOC_MMAP_THRESHOLD_`` in the environment instead turns
    glibc's dynamic threshold off, which costs more than it saves.  The cost is a resident set
    that stays at its peak, which a benchmark process can afford.

    Called by the bench commands unless ``--allocator default``; returns what is in effect,
    recorded with every run (``allocator``): "glibc mallopt …", or "default" where the C
    library is not glibc."""
    global _allocator
    import ctypes
    import ctypes.util

    if platform.system() != "Linux" or not platform.libc_ver()[0] == "glibc":
        return _allocator
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        ok = (libc.mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD) == 1
              and libc.mallopt(_M_TRIM_THRESHOLD, _TRIM_THRESHOLD) == 1)
    except (OSError, AttributeError):
        ok = False
    if ok:
        _allocator = "glibc mallopt M_MMAP_THRESHOLD=1GiB M_TRIM_THRESHOLD=2GiB"
    return _allocator


def thread_counts() -> dict[str, str]:
    """Thread counts in effect (recorded with every run)."""
    out = {f"env.{v}": os.environ.get(v, "") for v in RECORDED_VARS}
    import sys

    if "torch" in sys.modules:
        torch = sys.modules["torch"]
        out["threads.torch"] = str(torch.get_num_threads())
        out["threads.torch_interop"] = str(torch.get_num_interop_threads())
    return out


def collect() -> dict[str, str]:
    env = {
        "python": platform.python_version(),
        "platform": platform.platform(),
        "machine": platform.node(),
        "cpu": _cpu_model(),
        "cpu_count": str(os.cpu_count()),
        "commit": _git_commit(),
    }
    env["env.CUDA_VISIBLE_DEVICES"] = os.environ.get("CUDA_VISIBLE_DEVICES", "")
    env["allocator"] = _allocator
    env.update(thread_counts())
    for lib in LIBS:
        try:
            env[f"version.{lib}"] = metadata.version(lib)
        except metadata.PackageNotFoundError:
            env[f"version.{lib}"] = "not installed"
    return env


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity, else the machine's count)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def machine_key(env: dict[str, str]) -> str:
    """What must match for timings to be comparable: CPU model, logical CPUs, threads per library,
    allocator (runs recorded before it was, ran with the default one)."""
    return f"{env.get('cpu')}|{env.get('cpu_count')}|{env.get('threads', '')}|{env.get('allocator', 'default')}"
