"""Finding the LLVM library Dr.Jit's LLVM backend loads at run time (``DRJIT_LIBLLVM_PATH``).

Dr.Jit (Mitsuba 3's array library) compiles its CPU kernels with a shared libLLVM it opens at
run time, found through the environment variable ``DRJIT_LIBLLVM_PATH`` or the loader's search
path.  Dr.Jit 1.5 emits ``llvm.minimum``/``maximum`` intrinsics that LLVM 14 and 15 do not
lower on x86-64 ("Cannot select: fminimum"), which aborts the process — so a run must not
reach Dr.Jit with such a library.  :func:`configure` looks for libLLVM 16 or newer at the
standard Debian/Ubuntu and LLVM-apt paths and through ``ctypes.util.find_library``, sets
``DRJIT_LIBLLVM_PATH`` to the newest it finds (a value the user set is kept), and says why
when there is none.  It must run before ``drjit`` is first imported: Dr.Jit reads the variable
when it initialises its LLVM backend.
"""

from __future__ import annotations

import ctypes.util
import glob
import os
import re

#: the oldest LLVM major version Dr.Jit 1.5's LLVM backend runs with (14 and 15 abort)
MIN_MAJOR = 16
ENV = "DRJIT_LIBLLVM_PATH"
INSTALL_HINT = ("Debian/Ubuntu: apt-get install -y libllvm19 (or export DRJIT_LIBLLVM_PATH=/path/to/libLLVM.so "
                f"of LLVM {MIN_MAJOR} or newer)")

_PATTERNS = ("/usr/lib/llvm-*/lib/libLLVM*.so*", "/usr/lib/x86_64-linux-gnu/libLLVM*.so*",
             "/usr/lib/aarch64-linux-gnu/libLLVM*.so*", "/usr/lib64/libLLVM*.so*", "/usr/local/lib/libLLVM*.so*")


def _major(path: str) -> int | None:
    """LLVM's major version from a library path (libLLVM-19.so, libLLVM.so.19.1, llvm-19/lib/…)."""
    name = os.path.basename(path)
    for pat in (r"libLLVM-(\d+)", r"libLLVM\.so\.(\d+)"):
        m = re.search(pat, name)
        if m:
            return int(m.group(1))
    m = re.search(r"/llvm-(\d+)/", path)
    return int(m.group(1)) if m else None


def candidates() -> list[tuple[int, str]]:
    """``(major, path)`` of every libLLVM ≥ :data:`MIN_MAJOR` found, newest first (file paths before
    sonames)."""
    found = set()
    for pat in _PATTERNS:
        found.update(p for p in glob.glob(pat) if os.path.isfile(p))
    for major in range(30, MIN_MAJOR - 1, -1):
        lib = ctypes.util.find_library(f"LLVM-{major}")
        if lib:
            found.add(lib)  # a soname (dlopen searches the loader's path) where no file path is known
    out = {(m, p) for p in found if (m := _major(p)) is not None and m >= MIN_MAJOR}
    return sorted(out, key=lambda mp: (-mp[0], not os.path.isabs(mp[1]), mp[1]))


def configure() -> str | None:
    """Set ``DRJIT_LIBLLVM_PATH`` (module docstring); returns the reason Dr.Jit's LLVM backend
    cannot run here, or None (the variable is set, by the user or here)."""
    if os.environ.get(ENV):
        return None
    found = candidates()
    if not found:
        return (f"no libLLVM {MIN_MAJOR}+ found for Dr.Jit's LLVM backend (LLVM 14/15 abort on fminimum); "
                + INSTALL_HINT)
    os.environ[ENV] = found[0][1]
    return None
