"""The environment a run records: machine, threads, library versions, commit."""

from __future__ import annotations

import os
import platform
import subprocess
from importlib import metadata
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
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


def collect() -> dict[str, str]:
    env = {
        "python": platform.python_version(),
        "platform": platform.platform(),
        "machine": platform.node(),
        "cpu": _cpu_model(),
        "cpu_count": str(os.cpu_count()),
        "commit": _git_commit(),
    }
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "XLA_FLAGS", "CUDA_VISIBLE_DEVICES"):
        env[f"env.{var}"] = os.environ.get(var, "")
    for lib in LIBS:
        try:
            env[f"version.{lib}"] = metadata.version(lib)
        except metadata.PackageNotFoundError:
            env[f"version.{lib}"] = "not installed"
    return env


def machine_key(env: dict[str, str]) -> str:
    """What must match for timings to be comparable."""
    return f"{env.get('cpu')}|{env.get('cpu_count')}"
