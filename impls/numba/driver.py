"""The numba loop driver: isobench's root finders run ray by ray in compiled loops.

The algorithms are those of :mod:`impls.core.rootfind` (``SphereTrace``; ``MarchRefine`` with its
``ConstantStep`` or ``CertifiedStep`` rule, its ``Bisect``, ``Secant`` or ``Newton`` refiner and its
optional ladder stage), built by the method catalog from the validated knobs
(:meth:`impls.methods.MethodSpec.algorithm`) and read here field by field
(:func:`configuration`), so no knob has a default of its own in this module.

The certified methods (``SphereTrace``, and ``MarchRefine`` with a ``CertifiedStep`` rule: their
first-crossing certification, certified MISS and φ's resolution) run the array algorithm of
:mod:`impls.core.rootfind` itself with numpy's compacting driver, each φ evaluation one compiled
parallel kernel over the rays (:func:`_run_array`).

The constant-step marchers run in compiled kernels generated from one template of each step
(:mod:`impls.numba.template`): the array step of :mod:`impls.core.rootfind` written for one ray,
with the same operations in the same order, so the same depths, statuses
(:class:`impls.protocol.Status`), iteration and evaluation counts as the array drivers, the same
Lipschitz-violation check (:func:`impls.core.rootfind.lipschitz_violated`) and the same certified
convergence (a sign-change bracket no wider than ``xtol``, adjacent floats, or φ = 0).  Only the
refiners the template has are compiled (:data:`REFINERS`); another is an error, not a stand-in.
Where the array drivers step every ray still iterating once per loop step (compacting or
masking), these kernels run each ray to completion on its own (``prange`` over rays, threads
``NumbaSettings.threads``; on one thread, kernels compiled without numba's parallel pipeline:
:func:`kernels`), with its state in registers: no per-step overhead, which is what the
array drivers' ladder stage exists to amortise, so the driver's choice for the knob
``ladder = -1`` is no ladder (an explicit ``ladder`` is honoured).  Without ladder steps two rays
are stepped in turn per thread (the lanes kernel, whose rays' independent chains of operations
overlap; every refiner, Newton's with its derivative); the ladder runs one ray at a time
(``march_one``).

φ along a ray is the compiled scene (:mod:`impls.numba.fields`); dφ/dt, for Newton, is numpy's
central difference (:mod:`impls.numba.derivatives`), 3 evaluations.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..core.driver import _whole_at_least
from ..core.rootfind import (BAD, CONV, IN, LIPV, MAXI, MISS, NONF, UNC, Bisect, CertifiedStep, ConstantStep, MarchRefine,
                             Newton, Secant, SphereTrace)

#: per-ray ladder samples where the knob leaves it to the driver (-1): none (module docstring)
LADDER = 0


@dataclasses.dataclass(frozen=True)
class NumbaSettings:
    """How the per-ray driver runs, held by the numba backend (``backend.settings``) and recorded
    with every result row (``driver_json``).  Only ``ladder`` changes a per-ray result (it is
    part of the algorithm).

    threads: numba threads running rays side by side (``--threads`` of the bench commands; at
             most ``numba.config.NUMBA_NUM_THREADS``, fixed when numba starts);
    ladder:  samples per ladder step where the knob ``ladder`` is -1 (the driver's choice);
    lanes:   run the constant-step marchers without ladder steps in the lanes kernel (``LANES``
             rays stepped in turn per thread); False: in ``march_one``, one ray at a time, as
             those with ladder steps.  The two give the same per-ray results (the same step
             templates, :mod:`impls.numba.template`); the lanes kernel runs faster and is a compilation of
             its own per scene structure, which a run that times nothing skips
             (:meth:`impls.numba.backend.NumbaBackend.untimed_settings`);
    per_ray: run the constant-step marchers in the per-ray kernels (``march_one``, and the lanes
             kernel where ``lanes``); False: as the certified methods, the core array algorithm
             with numpy's compacting driver, each φ evaluation (with dφ/dt for Newton's, the
             kernels' own central difference) one compiled kernel over the rays
             (:func:`_run_array`).  The per-ray results are the same, bit for bit: the template
             is the array step written for one ray (:mod:`impls.numba.template`), and the
             evaluations are the kernels' own compiled φ.  Slower per step (numpy's per-step
             overhead, which the per-ray kernels do not have), but no marcher kernel to compile:
             ~3 s of numba's pipeline per scene structure, which a run that times nothing skips."""

    threads: int = 1
    ladder: int = LADDER
    lanes: bool = True
    per_ray: bool = True

    kind = "per-ray"

    def __post_init__(self):
        _whole_at_least(type(self).__name__, "threads", self.threads, 1)
        _whole_at_least(type(self).__name__, "ladder", self.ladder, 0)
        if not isinstance(self.lanes, bool):
            raise ValueError(f"{type(self).__name__}: lanes must be True or False (the lanes kernel on or off); got "
                             f"{self.lanes!r}")
        if not isinstance(self.per_ray, bool):
            raise ValueError(f"{type(self).__name__}: per_ray must be True or False (the per-ray marcher kernels on "
                             f"or off); got {self.per_ray!r}")
        import numba

        most = numba.config.NUMBA_NUM_THREADS
        if self.threads > most:
            raise ValueError(f"{type(self).__name__}: threads={self.threads} exceeds numba's thread pool of {most} "
                             "(NUMBA_NUM_THREADS, set in the environment before numba is imported)")

    def record(self) -> dict:
        """The settings as recorded with a result: ``{"driver": kind, field: value, …}`` with
        ``lanes`` the rays stepped in turn per thread by the lanes kernel (0: that kernel is not used)."""
        from .template import LANES

        return {"driver": self.kind, **dataclasses.asdict(self),
                "lanes": LANES if self.lanes and self.per_ray else 0}


# -- the algorithm's numbers, as the kernels take them -------------------------------------------

# float configuration: index names
(F_TMIN, F_TMAX, F_INVLIP, F_TOL, F_OMEGA, F_SCALE, F_LEPS, F_XTOL, F_STEP, F_CHECK, F_MINSTEP, F_CAP, F_EXTRA,
 F_REACH, F_RES) = range(15)
# int configuration
(I_BOUNDS, I_PROBE, I_MAXSTEPS, I_CERT, I_HASCHECK, I_REFINER, I_LADDER, I_LADDER_AFTER, I_COVER) = range(9)


def _lip_eps(alg, dtype) -> float:
    """16·gain·ε, the Lipschitz check's rounding factor (:func:`impls.core.rootfind.lipschitz_violated`)."""
    return 16.0 * alg.gain * float(np.finfo(np.dtype(dtype)).eps)


#: the refiners the kernels compile, by their number in the configuration (``I_REFINER``); by exact
#: class: a subclass may change the proposal (``_iterate``), which the kernels would not follow
REFINERS = {Bisect: 0, Secant: 1, Newton: 2}


def compiled_refiner(alg) -> int:
    """The kernels' number of the refiner of ``alg``, a ``MarchRefine`` (exactly: a subclass, such
    as ``march_chandrupatla``'s, replaces its steps) with a ``ConstantStep`` rule; any other
    algorithm or refiner is a NotImplementedError naming it and what the kernels compile (they
    must not run another refiner's steps in its place)."""
    compiled = ", ".join(c.__name__ for c in REFINERS)
    if type(alg) is not MarchRefine or type(alg.rule) is not ConstantStep:
        raise NotImplementedError(
            f"the numba kernels compile MarchRefine with a ConstantStep rule (refiners {compiled}); got "
            f"{type(alg).__name__} with {type(getattr(alg, 'rule', None)).__name__} (the certified methods run "
            "the core algorithm: _run_array)")
    ref = type(alg.refiner)
    if ref not in REFINERS:
        raise NotImplementedError(f"the numba kernels compile the refiners {compiled}; {ref.__module__}."
                                  f"{ref.__qualname__} is not one of them")
    return REFINERS[ref]


def configuration(alg, dtype="float64") -> tuple[str, np.ndarray, np.ndarray]:
    """``(kind, floats, ints)`` of a root finder built by the catalog: ``kind`` "sphere" or
    "march", its numbers in the kernels' layout (index names ``F_*``, ``I_*``).  A constant-step
    marcher's refiner is mapped by :func:`compiled_refiner` (an unknown one is an error)."""
    fc = np.zeros(15)
    ic = np.zeros(9, np.int64)
    fc[F_TMIN], fc[F_TMAX], fc[F_SCALE], fc[F_LEPS] = alg.t_min, alg.t_max, alg.scale, _lip_eps(alg, dtype)
    ic[I_BOUNDS], ic[I_MAXSTEPS] = alg.bounds is not None, alg.max_steps
    if isinstance(alg, SphereTrace):
        fc[F_INVLIP], fc[F_TOL], fc[F_OMEGA] = alg.inv_lip, alg.tol, alg.omega
        ic[I_PROBE] = alg.probe
        return "sphere", fc, ic
    rule = alg.rule
    fc[F_XTOL] = alg.xtol
    ic[I_LADDER], ic[I_LADDER_AFTER] = alg.ladder, alg.ladder_after
    if isinstance(rule, CertifiedStep):
        ic[I_CERT], ic[I_PROBE] = 1, rule.probe
        fc[F_INVLIP], fc[F_MINSTEP], fc[F_CAP] = rule.inv_lip, rule.min_step, rule.cap
        fc[F_EXTRA], fc[F_REACH] = rule.extrapolate, rule.reach
    else:
        ic[I_REFINER] = compiled_refiner(alg)
        fc[F_STEP] = rule.step
        fc[F_MINSTEP] = rule.min_step
        # the certified radius's rounding factor 8·gain·ε (impls.core.rootfind.resolution), for the
        # steps' cover of a MISS (ConstantStep.cover)
        ic[I_COVER], fc[F_RES] = rule.cover, 8.0 * alg.rg * float(np.finfo(np.dtype(dtype)).eps)
    if rule.check is not None:
        ic[I_HASCHECK], fc[F_CHECK] = 1, rule.check
    return "march", fc, ic


# -- kernels ------------------------------------------------------------------------------------

_KERNELS: dict = {}


def kernels(key: str, parallel: bool = True):
    """``{"march": …, "lanes": …, "phi_rays": …, "phi_rays_d": …}`` kernels for the scene source
    ``key`` (:class:`impls.numba.fields.CompiledScene`), made once per key and ``parallel`` (the cache
    lives as long as the process); numba compiles each on its first call.  ``parallel``: the rays'
    loops are numba's ``prange`` over threads; False, plain loops, for one thread (:func:`run_loop`:
    the same per-ray results; numba's parallel pipeline adds about a fifth to the compile time,
    for nothing on one thread).  With a cache directory (:mod:`impls.cache`) they come from a
    generated module there (:func:`_cached_module`), whose compiled kernels numba keeps on disk
    between runs."""
    k = _KERNELS.get((key, parallel))
    if k is None:
        from ..cache import subdir

        where = subdir("numba")
        if where is not None:
            mod = _cached_module(key, where, parallel)
            k = {"march": mod.run_march, "lanes": mod.run_lanes, "phi_rays": mod.phi_rays,
                 "phi_rays_d": mod.phi_rays_d}
        else:
            from .fields import CompiledScene, scene_functions

            phi, bounds = scene_functions(CompiledScene(key, np.zeros(0)))
            k = _make_kernels(phi, bounds, parallel)
        _KERNELS[(key, parallel)] = k
    return k


def kernels_source(key: str, parallel: bool = True) -> str:
    """The source of a module that defines the kernels of :func:`_make_kernels` for the scene
    source ``key`` at its top level, so that numba can cache them on disk (``cache=True`` needs a
    function of a module file, and keys a closure's cache entry on its cell contents, which for
    the jitted functions a closure captures differ in every process).

    The module is put together from the sources themselves, not rewritten: the scene's ``phi``
    and ``bounds`` (``key``), the body of :func:`_make_kernels` (its imports made absolute) and
    the kernels generated from the step templates (:func:`impls.numba.template.source`); the same
    algorithm text, compiled the same way, with the top-level kernels' caching turned on
    (:func:`impls.cache.lock_numba_cache`: numba's on-disk cache, safe for processes that compile
    at once)."""
    import inspect
    import textwrap

    from . import template

    body = inspect.getsource(_make_kernels).split("\n")
    start = next(i for i, ln in enumerate(body) if ln.startswith("def _make_kernels")) + 1
    stop = next(i for i, ln in enumerate(body) if ln.strip() == "from . import template")
    body = textwrap.dedent("\n".join(body[start:stop]))
    for rel, absolute in ((" .derivatives ", " impls.numba.derivatives "), (" .fields ", " impls.numba.fields ")):
        body = body.replace("from" + rel + "import", "from" + absolute + "import")
    consts = ", ".join(k for k in globals() if k[:2] in ("F_", "I_"))
    return "\n".join([
        '"""isobench numba kernels for one scene structure, generated by impls.numba.driver.kernels_source;',
        'numba keeps their compiled code in __pycache__ beside this file."""',
        "import math",
        "import numpy as np",
        "from numba import njit, prange",
        "from impls.numba.driver import BAD, CONV, IN, LIPV, MAXI, MISS, NONF, UNC",
        f"from impls.numba.driver import {consts}",
        "from impls.cache import lock_numba_cache",
        "from impls.numba.fields import helpers as _helpers",
        "globals().update({k: v for k, v in _helpers().items() if k not in globals()})",
        "_scene_jit = njit(error_model='numpy')",
        f"parallel = {bool(parallel)}",
        "",
        key,
        "phi, bounds = _scene_jit(phi), _scene_jit(bounds)",
        "",
        body,
        "from impls.numba.template import CHUNK",
        "",
        template.source(parallel),
        "",
        "for _k in (run_march, run_lanes, phi_rays, phi_rays_d):",
        "    lock_numba_cache(_k)",
        "",
    ])


def _cached_module(key: str, where, parallel: bool = True):
    """The module of :func:`kernels_source` for ``key`` and ``parallel``, written to ``where``
    (once, atomically, named by the hash of its text and numba's version) and imported from there."""
    import hashlib
    import importlib.util
    import inspect
    import os

    import numba

    src = kernels_source(key, parallel)
    # the name covers what the module's text does not: the code it imports and compiles into the
    # kernels (φ's derivative, the helpers), so that a change there is not answered from the cache
    from . import derivatives, fields

    deps = "".join(inspect.getsource(m) for m in (derivatives, fields))
    name = "isobench_numba_" + hashlib.sha256((numba.__version__ + "\n" + deps + src).encode()).hexdigest()[:24]
    path = where / f"{name}.py"
    if not path.exists() or path.read_text() != src:
        tmp = where / f".{name}.{os.getpid()}.tmp"
        tmp.write_text(src)
        os.replace(tmp, path)  # atomic: a process beside this one reads a whole file or none
    import sys

    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod  # numba finds a kernel's module by name, when it compiles and when it loads
    spec.loader.exec_module(mod)
    return mod


def compile_state(kernel) -> tuple[int, int]:
    """``(signatures compiled or loaded in this process, loads from the disk cache)`` of a kernel:
    what tells a compile from a reuse (:meth:`impls.numba.backend.NumbaBackend.compile`)."""
    return len(kernel.overloads), sum(kernel.stats.cache_hits.values())


def _make_kernels(phi, bounds, parallel=True):
    from numba import njit, prange

    from .derivatives import make_ray_eval
    from .fields import helpers

    h = helpers()
    _max, _min = h["_max"], h["_min"]
    ev, ev_d = make_ray_eval(phi)
    # the helpers, φ and the steps are plain njit functions, left to LLVM to inline into the
    # kernels (it does: the kernels' run time is within 2 % of numba's own IR inlining, median of
    # the quick suite's numba rows).  numba's inline="always" inlines at its IR level before type
    # inference, once per call site, and compiled the CSG marchers cold in 26 s instead of 4 s
    # (docs/performance.md, "numba compile time").
    jit = njit(error_model="numpy")
    inf, nan = math.inf, math.nan

    @jit
    def lipv(f0, f1, t0, t1, inv_lip, mag, leps):
        """impls.core.rootfind.lipschitz_violated (the inv_lip = 1 branch is this one times 1)."""
        a0, a1 = abs(f0), abs(f1)
        at = (abs(t0) + abs(t1)) + mag
        return abs(f1 - f0) * inv_lip > abs(t1 - t0) + leps * ((a0 + a1) * inv_lip + at)

    @jit
    def rcert(f, t, inv_lip, mag, rcoef):
        """impls.core.rootfind.certified_radius: |φ|/L less 8·gain·ε·(|t| + mag), at least 0."""
        return _max(abs(f) * inv_lip - rcoef * (abs(t) + mag), 0.0)

    @jit
    def cwidth(t, mag, rcoef, xtol):
        """impls.core.rootfind.MarchRefine.closing_width: max(4·rounding, 2ε|t|, xtol) + 4ε|t| (float64)."""
        at = abs(t)
        return _max(_max(4.0 * (rcoef * (at + mag)), (2.0 * 2.220446049250313e-16) * at), xtol) + (
            4.0 * 2.220446049250313e-16) * at

    @jit
    def covered(f0, t0, f1, t1, h, inv_lip, mag, rcoef):
        """impls.core.rootfind.ConstantStep.covered of the certified radii at a step's two ends."""
        return (rcert(f0, t0, inv_lip, mag, rcoef) + rcert(f1, t1, inv_lip, mag, rcoef) >= h) or not math.isfinite(h)

    @jit
    def verdict(nonf, conv, maxed, miss, lv, unc):
        """impls.core.rootfind._verdict: NON_FINITE, LIPSCHITZ_VIOLATED, UNCERTIFIED, MISS, CONVERGED,
        MAX_ITER."""
        if nonf:
            return NONF
        if lv:
            return LIPV
        if unc:
            return UNC
        if miss:
            return MISS
        if conv:
            return CONV
        if maxed:
            return MAXI
        return IN

    @jit
    def final_t(t, status):
        if status == MISS:
            return inf
        if status == NONF or status == BAD or status == LIPV:
            return nan
        return t

    @jit
    def start(p, o0, o1, o2, d0, d1, d2, t_min, t_max, use_bounds):
        """impls.core.rootfind._start: (t, hi, status) before any evaluation."""
        if use_bounds:
            lo, hi = bounds(p, o0, o1, o2, d0, d1, d2)
            lo, hi = _max(lo, t_min), _min(hi, t_max)
        else:
            lo, hi = t_min, t_max
        outside = not (lo <= hi)
        fin = (math.isfinite(o0) and math.isfinite(o1) and math.isfinite(o2) and math.isfinite(d0)
               and math.isfinite(d1) and math.isfinite(d2))
        status = BAD if not fin else (MISS if outside else IN)
        return (t_min if outside else lo), hi, status

    @njit(parallel=parallel, error_model="numpy")
    def phi_rays(O, D, T, p, F):
        """φ(o_i + t_i d_i) for every ray i: the certified methods' evaluation (:func:`run_loop`)."""
        for i in prange(T.shape[0]):
            F[i] = ev(p, O[i, 0], O[i, 1], O[i, 2], D[i, 0], D[i, 1], D[i, 2], T[i])

    @njit(parallel=parallel, error_model="numpy")
    def phi_rays_d(O, D, T, p, F, DF):
        """φ and dφ/dt at o_i + t_i d_i for every ray i, as ``march_one`` evaluates them for Newton's
        refinement (``ev_d``: the central difference of :mod:`impls.numba.derivatives`)."""
        for i in prange(T.shape[0]):
            F[i], DF[i] = ev_d(p, O[i, 0], O[i, 1], O[i, 2], D[i, 0], D[i, 1], D[i, 2], T[i])

    from . import template

    # the generated kernels' globals: what the cached module (kernels_source) defines at its top level
    ns = {"start": start, "ev": ev, "ev_d": ev_d, "lipv": lipv, "covered": covered, "rcert": rcert, "cwidth": cwidth, "verdict": verdict, "final_t": final_t,
          "_max": _max, "_min": _min, "math": math, "np": np, "njit": njit, "prange": prange, "inf": inf, "IN": IN,
          "NONF": NONF, "CONV": CONV, "UNC": UNC, "CHUNK": template.CHUNK,
          **{k: v for k, v in globals().items() if k[:2] in ("F_", "I_")}}
    exec(compile(template.source(parallel), "<isobench numba kernels>", "exec"), ns)  # noqa: S102 - our own generated source
    run_march, run_lanes = ns["run_march"], ns["run_lanes"]

    return {"march": run_march, "lanes": run_lanes, "phi_rays": phi_rays, "phi_rays_d": phi_rays_d}


def run_loop(key: str, params: np.ndarray, alg, o: np.ndarray, d: np.ndarray, settings: NumbaSettings) -> dict:
    """Run the catalog's root finder ``alg`` on rays ``o``, ``d`` (float64 (n, 3)) of the compiled
    scene (``key``, ``params``) with ``settings.threads`` threads; ``{t, status, iterations,
    evals}`` (t as reported: ``inf`` for MISS, NaN for NON_FINITE/BAD_INPUT/LIPSCHITZ_VIOLATED)."""
    import numba

    kind, fc, ic = configuration(alg, o.dtype)
    global LAST_COMPILE
    numba.set_num_threads(settings.threads)
    if kind == "sphere" or ic[I_CERT] or not settings.per_ray:
        ks = kernels(key, settings.threads > 1)
        deriv = bool(getattr(alg, "deriv", False))  # Newton's refinement: φ and dφ/dt
        kernel = ks["phi_rays_d" if deriv else "phi_rays"]
        before = compile_state(kernel)
        # compiled here, whether or not these rays evaluate φ (a run's first call compiles: prepare)
        z = np.zeros((1, 3), o.dtype)
        kernel(z, z, np.zeros(1, o.dtype), params, *(np.empty(1, o.dtype) for _ in range(1 + deriv)))
        out = _run_array(ks, params, alg, o, d, deriv)
    else:
        if kind == "march" and ic[I_LADDER] <= 1 and settings.lanes:
            kind = "lanes"  # (no ladder stage: impls.numba.template)
        n = o.shape[0]
        out = {"t": np.empty(n, o.dtype), "status": np.empty(n, np.int32), "iterations": np.empty(n, np.int32),
               "evals": np.empty(n, np.int32)}
        kernel = kernels(key, settings.threads > 1)[kind]
        before = compile_state(kernel)
        kernel(o, d, params, fc, ic, out["t"], out["status"], out["iterations"], out["evals"])
    after = compile_state(kernel)
    LAST_COMPILE = "reused" if before[0] or after[1] > before[1] else "compiled"
    return out


def _run_array(ks: dict, params: np.ndarray, alg, o: np.ndarray, d: np.ndarray, deriv: bool = False) -> dict:
    """A root finder run by the array algorithm of :mod:`impls.core.rootfind` itself, on numpy
    arrays with the numpy backend's compacting driver, each of its evaluations one compiled
    parallel kernel over the rays: φ (``phi_rays``), or φ and dφ/dt (``phi_rays_d``, the per-ray
    kernels' central difference) where ``deriv`` (``alg.deriv``: Newton's refinement).  The
    certified root finders (``SphereTrace``, ``MarchRefine`` with a ``CertifiedStep`` rule) always
    run so: their per-ray certification (the first-crossing check, the certified MISS, φ's
    resolution) is written once, there, and a per-ray copy here would be a second implementation
    of it to keep in step.  The constant-step marchers run so where ``NumbaSettings.per_ray`` is
    False (the same per-ray results as the per-ray kernels, without compiling them)."""
    from ..core.driver import CompactingSettings
    from ..numpy.driver import run_loop as run_compacted_numpy

    phi_rays, phi_rays_d = ks["phi_rays"], ks["phi_rays_d"]

    def ev(oo, dd, t, want_df):
        # (contiguous copies: one compiled specialisation, whatever view the compacting driver passes)
        oo, dd, t = np.ascontiguousarray(oo), np.ascontiguousarray(dd), np.ascontiguousarray(t)
        f = np.empty_like(t)
        if want_df:
            if not deriv:
                raise NotImplementedError("dφ/dt asked of an algorithm that declares no derivative (alg.deriv)")
            df = np.empty_like(t)
            phi_rays_d(oo, dd, t, params, f, df)
            return f, df, 3
        phi_rays(oo, dd, t, params, f)
        return f, None, 1

    return run_compacted_numpy(alg, o, d, ev, CompactingSettings(threads=1))


#: whether the last :func:`run_loop` call compiled its kernel ("compiled") or found it compiled in
#: this process or on disk ("reused")
LAST_COMPILE: str | None = None
