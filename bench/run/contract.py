"""The backend contract as the runner checks it: what a backend's ``methods()``,
``capabilities``, ``prepare`` and ``Prepared.result`` give back is user code, validated here
(docs/backends.md, "What the runner validates"); a breach is a :class:`BackendFault`, which costs
the backend that configuration's row and nothing else."""

from __future__ import annotations

import contextlib
import os
import sys
from typing import Any, Callable, Iterator

import numpy as np

from impls.protocol import Declined, RayResult, Status

from . import interrupts
from .metrics import finite_rows
from .timing import Timeout

class BackendFault(ValueError):
    """A backend broke the :class:`impls.protocol.Backend` contract (a wrong type, shape, dtype or
    status code, a missing attribute, a method that raised): its configuration is a failed row
    with this message, and the run goes on."""


@contextlib.contextmanager
def library_state_kept() -> Iterator[None]:
    """Run a configuration and then put back the process-wide settings a backend's code can change
    for every row after its own: numpy's floating-point error handling (a plug-in's
    ``np.seterr(all="raise")`` made numpy's own rows fail with FloatingPointError), torch's default
    dtype and thread count, jax's ``jax_enable_x64``; and the interpreter's: the working directory
    (a plug-in's ``os.chdir`` moved a relative ``--out``), the recursion limit (60 made the results
    write fail, losing every row), ``sys.stdout`` and ``sys.stderr`` (one closed or replaced lost
    the run's progress and report lines).  Libraries not yet imported are not imported.
    Within the configuration the change stands, so it costs that configuration's rows at most."""
    err = np.geterr()
    try:
        cwd = os.getcwd()
    except OSError:  # (a directory removed under the process: nothing to go back to)
        cwd = None
    recursion = sys.getrecursionlimit()
    streams = (sys.stdout, sys.stderr)
    torch, jax = sys.modules.get("torch"), sys.modules.get("jax")
    try:  # (a stand-in module in sys.modules, as tests plant, is left alone)
        torch_state = (torch.get_default_dtype(), torch.get_num_threads()) if torch is not None else None
    except AttributeError:
        torch_state = None
    try:
        x64 = bool(jax.config.jax_enable_x64) if jax is not None else None
    except AttributeError:
        x64 = None
    try:
        yield
    finally:
        np.seterr(**err)
        _restore_interpreter(cwd, recursion, streams)
        if torch_state is not None:
            if torch.get_default_dtype() != torch_state[0]:
                torch.set_default_dtype(torch_state[0])
            if torch.get_num_threads() != torch_state[1]:
                torch.set_num_threads(torch_state[1])
        if x64 is not None and bool(jax.config.jax_enable_x64) != x64:
            jax.config.update("jax_enable_x64", x64)


def _restore_interpreter(cwd: str | None, recursion: int, streams: tuple) -> None:
    """Put back what :func:`library_state_kept` saved of the interpreter; a stream the backend
    closed is opened again on its file descriptor (which closing ``sys.stdout`` leaves open)."""
    if cwd is not None:
        try:
            os.chdir(cwd)
        except OSError:  # (removed meanwhile: the backend's doing; nothing to go back to)
            pass
    if sys.getrecursionlimit() != recursion:
        sys.setrecursionlimit(recursion)
    for name, saved in zip(("stdout", "stderr"), streams):
        now = getattr(sys, name)
        if now is saved and not getattr(saved, "closed", False):
            continue
        if getattr(saved, "closed", False):
            try:
                saved = open(1 if name == "stdout" else 2, "w", encoding=getattr(saved, "encoding", None) or "utf-8",
                             errors="backslashreplace", closefd=False, buffering=1)
            except (OSError, ValueError):
                continue
        setattr(sys, name, saved)


def backend_call(backend: Any, what: str, fn: Callable[[], Any]) -> Any:
    """``fn()`` (a call into user code), any exception turned into a :class:`BackendFault` that
    names ``what`` was called."""
    try:
        return fn()
    except (Timeout, Declined):  # a declined configuration is skipped, not failed (run_one)
        raise
    except KeyboardInterrupt as exc:  # a Ctrl-C stops the run; the backend's own raise is its fault
        if interrupts.signalled():
            raise
        raise BackendFault(f"{what} raised KeyboardInterrupt: {exc} (no Ctrl-C was pressed: the backend "
                           "raised it itself)") from exc
    except BaseException as exc:  # user code: whatever it raises (SystemExit too) is its fault, not the run's
        raise BackendFault(f"{what} raised {type(exc).__name__}: {exc}") from exc


def backend_methods(backend: Any) -> tuple[str, ...]:
    """``backend.methods()`` checked: an iterable of method names (else :class:`BackendFault`)."""
    got = backend_call(backend, "backend.methods()", backend.methods)
    if isinstance(got, str) or not all(isinstance(m, str) for m in backend_call(backend, "iterating methods()",
                                                                               lambda: list(got))):
        raise BackendFault(f"backend.methods() must return method names (strings), got {got!r:.200}")
    return tuple(got)


def backend_dtypes(backend: Any) -> tuple[str, ...]:
    """``backend.capabilities.dtypes`` checked (else :class:`BackendFault`)."""
    caps = backend_call(backend, "backend.capabilities", lambda: backend.capabilities)
    dts = backend_call(backend, "backend.capabilities.dtypes", lambda: caps.dtypes)
    if isinstance(dts, str) or not all(isinstance(d, str) for d in backend_call(
            backend, "iterating capabilities.dtypes", lambda: list(dts))):
        raise BackendFault(f"backend.capabilities.dtypes must be dtype names (strings), got {dts!r:.200}")
    return tuple(dts)


#: the largest count ``iterations`` and ``evals`` may hold: the int32 of RayResult's counters
COUNT_MAX = 2**31 - 1

#: the codes a result may hold (IN_PROGRESS is internal to the drivers, never returned)
_STATUS_CODES = frozenset(int(s) for s in Status if s != Status.IN_PROGRESS)


#: the shape of one ray's entry in each output a method of the catalog declares
#: (``MethodSpec.outputs``; :class:`impls.protocol.RayResult`, docs/backends.md): a result's output
#: is (n, *shape); ``"P"`` is the scene's parameter count, ``scene.param_vector().size`` (dt/dθ
#: has one column per entry of θ).  An output not listed here is checked on its leading dimension
#: only (tests/test_plugin_robustness.py holds the catalog's outputs to this table).
OUTPUT_SHAPES: dict[str, tuple] = {
    "normal": (3,), "color": (3,), "dt_dtheta": ("P",),
    "curvature_laplacian": (), "curvature_divergence": (), "gaussian_curvature": (),
    "opacity": (), "samples_used": (), "work_saved": (),
}


def result_arrays(res: Any) -> RayResult:
    """What ``Prepared.result`` returned with each of its arrays converted to numpy, nothing else
    checked: the part of :func:`check_result` that runs the backend's code (``np.asarray`` calls
    an array's ``__array__``: a lazy device array's queued work, a user type's conversion; reading
    an attribute may call a property).  The runner calls it inside the configuration's time limit,
    so that a conversion that is slow or hangs is a Timeout row like a slow ``run``; what
    :func:`check_result` does after it is numpy's own work on numpy arrays.  A missing array, or
    one that does not convert, is a :class:`BackendFault`; a :class:`Timeout` passes through."""
    arrays = {}
    for name in ("t", "status", "iterations", "evals"):
        if not hasattr(res, name):
            raise BackendFault(f"the result has no {name!r} (a RayResult has t, status, iterations, evals, "
                               f"outputs); got {type(res).__name__}")
        try:
            arrays[name] = np.asarray(getattr(res, name))
        except Exception as exc:
            raise BackendFault(f"result {name} is not an array: {type(exc).__name__}: {exc}") from exc
    outs = getattr(res, "outputs", None)
    if outs is None:
        outs = {}
    if not isinstance(outs, dict):
        raise BackendFault(f"result outputs must be a dict of arrays, got {type(outs).__name__}")
    clean = {}
    for name, a in outs.items():
        try:
            clean[name] = np.asarray(a)
        except Exception as exc:
            raise BackendFault(f"output {name} is not an array: {type(exc).__name__}: {exc}") from exc
    return RayResult(outputs=clean, **arrays)


def _array(arrays: RayResult, name: str, n: int) -> np.ndarray:
    """``arrays.<name>`` (converted by :func:`result_arrays`), checked: shape (n,) and a real
    numeric dtype (else BackendFault)."""
    a = getattr(arrays, name)
    if a.shape != (n,):
        raise BackendFault(f"wrong shape: result {name} has shape {a.shape}, expected ({n},)")
    if a.dtype.kind not in "biuf":
        raise BackendFault(f"result {name} has dtype {a.dtype}, expected a real number dtype")
    return a


def output_shape(name: str, n: int, scene: Any = None) -> tuple | None:
    """The shape output ``name`` must have for ``n`` rays (:data:`OUTPUT_SHAPES`) on ``scene``;
    None where the table does not know it.  dt/dθ's column count is ``None`` (any) when no scene
    is given or its parameters cannot be read (the reference answer then says what is wrong)."""
    shape = OUTPUT_SHAPES.get(name)
    if shape is None:
        return None
    if "P" in shape:
        try:
            p = int(np.asarray(scene.param_vector()).size) if scene is not None else None
        except Exception:  # noqa: BLE001 - a scene without parameters: the metrics say so
            p = None
        shape = tuple(p if d == "P" else d for d in shape)
    return (n, *shape)


def _shape_text(shape: tuple) -> str:
    return "(" + ", ".join("any" if d is None else str(d) for d in shape) + ("," if len(shape) == 1 else "") + ")"


def check_result(res: Any, n: int, outputs: tuple[str, ...], *, scene: Any = None,
                 who: str = "the backend", dtype: str | None = None, t_range: tuple | None = None,
                 evaluates: bool = False) -> RayResult:
    """The per-ray contract, checked on what a backend's ``Prepared.result`` returned, which is
    user code: ``t``, ``status``, ``iterations``, ``evals`` arrays of shape (n,) and real dtype;
    ``status`` integer codes of :class:`impls.protocol.Status`; ``iterations``/``evals`` whole
    counts in [0, :data:`COUNT_MAX`]; ``outputs`` a dict holding every declared output with its whole shape
    (:data:`OUTPUT_SHAPES`, e.g. ``normal`` (n, 3); dt/dθ's columns those of ``scene``'s
    parameters) and a numeric dtype; no silent NaN (a non-finite ``t`` or output row on a ray whose
    status is CONVERGED).  With ``dtype``: ``t`` and real outputs computed in it (:func:`_check_precision`:
    a float32 answer is no float64 row, a float64 one no float32 row).  With ``t_range`` (t_min,
    t_max; root finders): a CONVERGED ``t`` within it (to 4 spacings of the dtype at t) and a
    MISS's ``t`` = inf (the status table).  With ``evaluates`` (a root finder that evaluates φ, as
    every method an array library runs does): at least one evaluation counted on every CONVERGED
    ray, since a bracket or φ = 0 needs one (a plug-in counting none won "which to pick" on
    evaluations in an accuracy-only run); the counts are otherwise the backend's own, not
    verified.  ``res`` may be what :func:`result_arrays` made of it (the runner converts inside the
    time limit); ``who`` names the backend in a shape error.  Returns a clean
    :class:`RayResult` of numpy arrays (``t`` float64, counts int64); raises :class:`BackendFault`
    (a ValueError) naming the offending array."""
    arrays = result_arrays(res)  # numpy arrays already: np.asarray returns them as they are
    t = _array(arrays, "t", n)
    _check_precision(t, "t", dtype)
    t = t.astype(np.float64)
    status = _array(arrays, "status", n)
    if status.dtype.kind == "b":
        raise BackendFault("result status has dtype bool; status codes are the integers of impls.protocol.Status "
                           "(e.g. Status.CONVERGED, Status.MISS)")
    if status.dtype.kind == "f":
        if not np.all(np.isfinite(status)) or np.any(status != np.round(status)):
            raise BackendFault(f"result status holds non-integer values (dtype {status.dtype}); status codes are "
                               f"the integers of impls.protocol.Status")
    status = status.astype(np.int64)
    bad = sorted(set(np.unique(status).tolist()) - _STATUS_CODES)
    if bad:
        raise BackendFault(f"result status holds code(s) {bad[:5]} that are not impls.protocol.Status values "
                           f"(IN_PROGRESS is internal); valid: "
                           f"{ {s.name: int(s) for s in Status if s != Status.IN_PROGRESS} }")
    counts = {}
    for name in ("iterations", "evals"):
        a = _array(arrays, name, n)
        # whole numbers within int32, the counters' type (RayResult): a fraction of an evaluation is
        # no count (0.001 evals a ray won "which to pick"), and 1e300 overflowed the results file,
        # losing every backend's rows
        fraction = a.dtype.kind == "f" and bool(np.any(np.isfinite(a) & (a != np.round(a))))
        if not np.all(np.isfinite(a)) or np.any(a < 0) or np.any(a > COUNT_MAX) or fraction:
            raise BackendFault(f"result {name} must be whole counts in [0, {COUNT_MAX}] (int32); got min {np.min(a)}, "
                               f"max {np.max(a)}" + (", not whole numbers" if fraction else ""))
        counts[name] = a.astype(np.int64)
    conv = status == Status.CONVERGED
    if evaluates and np.any(conv & (counts["evals"] < 1)):
        k = int(np.sum(conv & (counts["evals"] < 1)))
        raise BackendFault(f"{k} rays are CONVERGED with no evaluation of φ counted (evals 0): a root finder's hit "
                           "needs at least one; count every evaluation in evals (docs/backends.md)")
    nbad = int(np.sum(conv & ~np.isfinite(t)))
    if nbad:
        raise BackendFault(f"silent NaN: {nbad} rays have non-finite t with status CONVERGED")
    if t_range is not None:
        _check_range(t, status, t_range, dtype)
    clean = arrays.outputs
    for name in outputs:
        if name not in clean:
            raise BackendFault(f"missing output {name!r}; returned {sorted(map(str, clean))}")
        a = clean[name]
        want = output_shape(name, n, scene)
        if want is None:  # an output the table does not know: its leading dimension
            if a.shape[:1] != (n,):
                raise BackendFault(f"wrong shape: output {name} of {who} has shape {a.shape}, expected ({n}, …)")
        elif a.ndim != len(want) or any(w is not None and g != w for g, w in zip(a.shape, want)):
            raise BackendFault(f"wrong shape: output {name} of {who} has shape {a.shape}, expected "
                               f"{_shape_text(want)} ({n} rays; impls.protocol.RayResult gives each output's shape)")
        if a.dtype.kind not in "biuf":
            # (complex: the metrics' float64 conversion would drop the imaginary part and judge the rest)
            raise BackendFault(f"output {name} has dtype {a.dtype}, expected real numbers")
        _check_precision(a, f"output {name}", dtype)
        nbad = int(np.sum(conv & ~finite_rows(a)))
        if nbad:
            raise BackendFault(f"silent NaN: {nbad} rays have non-finite {name} with status CONVERGED")
    return RayResult(t=t, status=status, iterations=counts["iterations"], evals=counts["evals"], outputs=clean)


def _check_precision(a: np.ndarray, what: str, dtype: str | None) -> None:
    """A configuration's real arrays hold what its dtype computes: in a float64 configuration
    float64 (or wider), since a float32 answer under a float64 label would be compared, ranked and
    baselined as float64's accuracy; in a float32 one float32, or a wider dtype holding only values
    float32 represents exactly (a float32 answer widened), since a float64 answer under a float32
    label makes float32's accuracy and its scoreboard look like float64's, and a float16 one is
    not float32's either."""
    if a.dtype.kind != "f" or dtype not in ("float32", "float64"):
        return
    bits = np.finfo(a.dtype).bits
    if dtype == "float64" and bits < 64:
        raise BackendFault(f"result {what} has dtype {a.dtype} in a float64 configuration: compute in float64, "
                           "or declare only the dtypes the backend computes in (capabilities.dtypes)")
    if dtype == "float32" and bits < 32:
        raise BackendFault(f"result {what} has dtype {a.dtype} in a float32 configuration: compute in float32, "
                           "or declare only the dtypes the backend computes in (capabilities.dtypes)")
    if dtype == "float32" and bits > 32:
        with np.errstate(over="ignore", invalid="ignore"):
            narrow = a.astype(np.float32).astype(a.dtype)
        wider = ~((narrow == a) | (np.isnan(a) & np.isnan(narrow)))
        if wider.any():
            i = np.unravel_index(int(np.flatnonzero(wider.reshape(-1))[0]), a.shape)
            raise BackendFault(f"result {what} holds values float32 cannot represent in a float32 configuration "
                               f"({int(wider.sum())} of them; at {tuple(int(k) for k in i)}: {a[i].item()!r}): it was computed "
                               "in a wider dtype; compute in float32 (a float32 answer may be returned widened), or "
                               "declare only the dtypes the backend computes in (capabilities.dtypes)")


def _check_range(t: np.ndarray, status: np.ndarray, t_range: tuple, dtype: str | None) -> None:
    """A root finder's CONVERGED depth lies in [t_min, t_max] (to 4 spacings of the run's dtype at
    t: an engine's float32 hit at t_max may round past it), and a MISS has t = +inf."""
    t_min, t_max = (float(v) for v in t_range)
    eps = float(np.finfo(np.float32 if dtype == "float32" else np.float64).eps)
    slack = 4.0 * eps * np.maximum(1.0, np.abs(t))
    conv = status == Status.CONVERGED
    out = conv & ((t < t_min - slack) | (t > t_max + slack))
    if out.any():
        i = int(np.flatnonzero(out)[0])
        raise BackendFault(f"{int(out.sum())} rays CONVERGED at a depth outside [t_min, t_max] = [{t_min:g}, {t_max:g}] "
                           f"(ray {i}: t = {t[i]!r}); a root finder's hit lies in the searched interval")
    miss = (status == Status.MISS) & (t != np.inf)
    if miss.any():
        i = int(np.flatnonzero(miss)[0])
        raise BackendFault(f"{int(miss.sum())} rays are MISS with t ≠ inf (ray {i}: t = {t[i]!r}); a MISS has t = inf "
                           "(impls.protocol.Status, docs/backends.md)")


#: how far a timed call's real numbers may lie from the checked call's, in spacings of the
#: configuration's dtype at the larger of the two: a device's reductions may round in another order
#: from call to call; a backend that answers differently beyond that computes something else
CALL_ULPS = 64


def owned(res: RayResult) -> RayResult:
    """``res`` (numpy arrays, :func:`result_arrays`) with every array copied: a backend whose
    ``result`` returns views of buffers its next call overwrites cannot change it."""
    return RayResult(t=np.array(res.t), status=np.array(res.status), iterations=np.array(res.iterations),
                     evals=np.array(res.evals), outputs={k: np.array(v) for k, v in res.outputs.items()})


def answers_differ(first: RayResult, later: RayResult, dtype: str | None) -> str:
    """Where a later (timed) call's answer differs from the first (checked) call's, as a phrase, or
    "": statuses and counts exactly, real numbers to :data:`CALL_ULPS` spacings of ``dtype`` (NaN
    equals NaN).  The timed calls are what a row's time claims; the first call is what its
    accuracy judges, so they must be one answer (a plug-in that computed once, then returned
    garbage fast was picked at ×0.001 with numpy's errors: the 2026-12-01 plug-in probe).  A
    backend that returns a remembered answer to the same inputs is not caught by this."""
    eps = float(np.finfo(np.float32 if dtype == "float32" else np.float64).eps)
    pairs = [(n, getattr(first, n), getattr(later, n)) for n in ("t", "status", "iterations", "evals")]
    pairs += [(f"output {k}", v, later.outputs.get(k)) for k, v in first.outputs.items()]
    for name, a, b in pairs:
        if b is None:
            return f"{name} is missing from a timed call's result"
        a, b = np.asarray(a), np.asarray(b)
        if a.shape != b.shape:
            return f"{name} has shape {a.shape} in the checked call, {b.shape} in a timed one"
        if a.dtype.kind == "f" or b.dtype.kind == "f":
            x, y = a.astype(np.float64), b.astype(np.float64)
            with np.errstate(invalid="ignore", over="ignore"):
                same = (x == y) | (np.isnan(x) & np.isnan(y)) | (
                    np.abs(x - y) <= CALL_ULPS * eps * np.maximum(np.abs(x), np.abs(y)))
        else:
            same = a == b
        if not np.all(same):
            i = np.unravel_index(int(np.flatnonzero(~np.asarray(same).reshape(-1))[0]), a.shape)
            return (f"{name} differs on {int(np.size(same) - np.count_nonzero(same))} of {np.size(same)} values "
                    f"(at {tuple(int(k) for k in i)}: {a[i].item()!r} checked, {b[i].item()!r} timed)")
    return ""


def status_counts(status: np.ndarray) -> dict[str, int]:
    """{status name: rays}, computed here from checked codes (a backend's own RayResult subclass
    need not have ``status_counts``, and its answer would be unchecked)."""
    vals, counts = np.unique(status, return_counts=True)
    return {Status(int(v)).name: int(c) for v, c in zip(vals, counts)}


def compile_seconds(prep: Any) -> float | None:
    """``Prepared.compile_s``: a finite number ≥ 0 or None (a missing attribute is None)."""
    v = getattr(prep, "compile_s", None)
    if v is None:
        return None
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise BackendFault(f"Prepared.compile_s must be seconds (a number) or None, got {v!r:.100}") from None
    if not (np.isfinite(f) and f >= 0):
        raise BackendFault(f"Prepared.compile_s must be finite and ≥ 0, got {f}")
    return f

