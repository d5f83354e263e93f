"""The backend protocol: what every backend (built-in or plugged in) provides.

A backend wraps one array library on one device.  It converts arrays, synchronises the
device, compiles (or not), differentiates (or not), and provides *methods*: named ray
algorithms with one signature, ``prepare(method, scene, origins, directions, dtype=…, t_min=…,
t_max=…, t_hit=None, color=None, **knobs) -> Prepared``.  ``t_hit`` (per-ray depths) is required
by methods whose :class:`impls.methods.MethodSpec` has ``needs_t_hit``; ``color`` (a colour field
with ``value(x, xp) -> (..., 3)``, default ``reference.rendering.SineColor()``) is taken by methods
with ``needs_color`` (the ``render`` family) and refused by the others.  ``Prepared.run()`` does the timed work and returns backend-native arrays;
``Prepared.result(out)`` turns them into a float64/int numpy :class:`RayResult`.  The split lets
``bench`` time ``run`` alone (conversion, compilation and transfer excluded): it times
``out = prep.run(); backend.synchronize(out)``.  docs/backends.md documents every method, what
the runner validates, and ``python -m bench conformance --backend SPEC``.

Per-ray status codes follow scipy's elementwise solvers (``scipy/_lib/_elementwise_iterative_
method.py``): 0 converged, negative codes are failures, positive codes are non-failure
outcomes.  No silent NaN: a non-finite depth always comes with a status that says why.
"""

from __future__ import annotations

import dataclasses
import enum
from typing import Any, Callable, Protocol, runtime_checkable

import numpy as np


class Status(enum.IntEnum):
    """Per-ray outcome of a root finder."""

    #: a hit within the method's tolerance; ``t`` is the depth (for ``raycast``, an engine's own
    #: query, the engine's hit: no bracket or bound behind it, :mod:`impls.engine`)
    CONVERGED = 0
    IN_PROGRESS = 1  #: internal: still iterating (never returned)
    MISS = 2  #: the ray left [t_min, t_max] with no hit; ``t`` is ``inf``
    MAX_ITER = -2  #: the step budget ran out; ``t`` is the last iterate
    NON_FINITE = -3  #: φ or t became NaN/inf; ``t`` is NaN
    #: the ray itself is invalid (non-finite origin or direction, zero direction), or the band
    #: renderers' finite t_hit lies outside [t_min, t_max]; outputs NaN
    BAD_INPUT = -5
    ILL_CONDITIONED = -6  #: derivative along the ray ≈ 0 (grazing), e.g. for dt/dθ
    #: a step observed |φ(t₁) − φ(t₀)| > L·|t₁ − t₀|: the scene's declared Lipschitz bound L is
    #: false there, so no certified answer exists; ``t`` is NaN
    LIPSCHITZ_VIOLATED = -7
    #: no certified answer (docs/methods.md "What each root finder can miss"): the ray found no
    #: crossing but stepped over part of its interval without a Lipschitz certificate (not a
    #: certified MISS; ``t`` is ``inf``), or it reached a point where φ is within its own rounding
    #: of 0 without a resolved sign change (a hit and a near miss cannot be told apart in this
    #: dtype; ``t`` is that depth)
    UNCERTIFIED = -8


class Declined(NotImplementedError):
    """A backend does not run this method on this scene although it offers the method (e.g. a
    compiling backend and a scene node it cannot compile: a mesh, a user's field).  Raised by
    ``prepare``; the message is the reason, and a run records the configuration as skipped with it.

    A backend that can tell without being given rays says so ahead of time with the optional hook
    ``declines(method, scene) -> str | None`` (the reason, or None), which the runner asks while
    planning (:func:`declined_reason`)."""


def declined_reason(backend: Any, method: str, scene: Any) -> str | None:
    """The reason ``backend`` declines ``method`` on ``scene`` (its optional ``declines`` hook), or
    None (no hook, or not declined).  A hook must return a string or None (else TypeError)."""
    hook = getattr(backend, "declines", None)
    if not callable(hook):
        return None
    reason = hook(method, scene)
    if reason is not None and not isinstance(reason, str):
        raise TypeError(f"backend.declines(method, scene) must return a reason (str) or None, got "
                        f"{type(reason).__name__}")
    return reason or None


@dataclasses.dataclass
class RayResult:
    """Per-ray outputs of any method, as numpy arrays with leading dimension ``n`` (rays).

    Every method returns ``t`` (depth: the hit found, or the ``t_hit`` it was given), ``status``,
    ``iterations`` and ``evals`` (field evaluations per ray).  Other outputs go to ``outputs``
    under the names its :class:`impls.methods.MethodSpec` lists (e.g. ``normal`` (n, 3),
    ``curvature_laplacian`` (n,), ``dt_dtheta`` (n, P), ``color`` (n, 3)).

    Values by status (every method, every backend; ``status`` says why a value is missing):

    * CONVERGED — every output finite (a non-finite one turns the status NON_FINITE);
    * MISS — ``t`` = inf; renderers' ``color``/``opacity`` 0 (the background); other outputs NaN;
    * BAD_INPUT (non-finite origin or direction, zero direction), NON_FINITE, LIPSCHITZ_VIOLATED
      — every float output NaN, ``t`` included;
    * MAX_ITER — ``t`` the last iterate (its error still shrinks with the budget), other outputs NaN;
    * UNCERTIFIED — ``t`` inf (no crossing found, but not over certified steps), the depth of a
      crossing not proved the first (the hybrids: a step stood uncertified before it), or the depth at
      which φ fell within its rounding (no resolved sign change); other outputs NaN;
    * ILL_CONDITIONED — dt/dθ at a grazing hit: the value is returned but not trustworthy.
    """

    t: np.ndarray
    status: np.ndarray
    iterations: np.ndarray
    evals: np.ndarray
    outputs: dict = dataclasses.field(default_factory=dict)

    def status_counts(self) -> dict[str, int]:
        vals, counts = np.unique(self.status, return_counts=True)
        return {Status(int(v)).name: int(c) for v, c in zip(vals, counts)}


@dataclasses.dataclass(frozen=True)
class Capabilities:
    """What a backend can do; one table drives tests, bench and reports.

    autodiff: "reverse"/"forward"/"both" or ``None``; jit: compiles functions; dtypes and
    devices supported; ``notes``: human-readable statements the report shows (e.g. where
    finite differences replace autodiff); ``expected_failures``: known conformance failures.
    """

    dtypes: tuple[str, ...] = ("float64", "float32")
    devices: tuple[str, ...] = ("cpu",)
    autodiff: str | None = None
    jit: bool = False
    notes: tuple[str, ...] = ()
    #: conformance checks this backend is known to fail, as (check id, reason) pairs; the
    #: conformance suite marks them xfail(strict) with the reason, so they are listed in one place
    #: and a fixed one shows up.  Check ids: ``eval_count``, ``gradcheck``, ``jit`` ….
    expected_failures: tuple[tuple[str, str], ...] = ()

    def expected_failure(self, check: str) -> str | None:
        return dict(self.expected_failures).get(check)


@dataclasses.dataclass
class Prepared:
    """A method bound to a scene, rays, dtype and knobs, ready to be timed.

    ``run()`` -> native output (work queued or done on the device); ``result(native)`` ->
    :class:`RayResult`.  ``compile_s`` is set by backends that compile ahead of time;
    ``compile_cache`` by those that keep compiled kernels: "compiled" (compiled for this call),
    "reused" (taken from a cache, on disk or in this process), None (not stated).
    """

    run: Callable[[], Any]
    result: Callable[[Any], RayResult]
    compile_s: float | None = None
    compile_cache: str | None = None


@runtime_checkable
class Backend(Protocol):
    """Structural protocol; :class:`impls.base.ArrayBackend` is a convenient base class."""

    #: the backend's name in rows, reports, ``--backend`` and ``bench compare``, however it was
    #: loaded: letters, digits and ``_.:+-`` (:data:`impls.registry.ID_PATTERN`)
    id: str
    lib: str
    device: str
    capabilities: Capabilities

    def methods(self) -> tuple[str, ...]: ...

    def prepare(self, method: str, scene: Any, origins: np.ndarray, directions: np.ndarray, *,
                dtype: str = "float64", t_min: float = 0.0, t_max: float = float("inf"), t_hit: Any = None,
                color: Any = None, **knobs: Any) -> Prepared:
        """``color``: colour field of methods with ``MethodSpec.needs_color`` (``value(x, xp) ->
        (..., 3)``; ``None`` = ``reference.rendering.SineColor()``); a ValueError for others."""
        ...

    def synchronize(self, out: Any) -> None:
        """Block until the device work that produced ``out`` (what ``Prepared.run()`` returned)
        is finished, so that the time measured around ``run()`` and ``synchronize(out)`` is the
        work's, not the queueing's.  ``out`` is required: a lazy library waits on the arrays
        themselves (jax's ``block_until_ready``), a synchronous one (numpy) does nothing."""
        ...

    def versions(self) -> dict[str, str]: ...
