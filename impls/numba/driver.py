"""The numba loop driver: isobench's root finders run ray by ray in compiled loops.

The algorithms are those of :mod:`impls.core.rootfind` (``SphereTrace``; ``MarchRefine`` with its
``ConstantStep`` or ``CertifiedStep`` rule, its ``Bisect``, ``Secant`` or ``Newton`` refiner and its
optional ladder stage), built by the method catalog from the validated knobs
(:meth:`impls.methods.MethodSpec.algorithm`) and read here field by field, so no knob has a
default of its own in this module.  Each step is the array step of :mod:`impls.core.rootfind`
written for one ray, with the same operations in the same order: the same depths, statuses
(:class:`impls.protocol.Status`), iteration and evaluation counts as the array drivers, the same
Lipschitz-violation check (:func:`impls.core.rootfind.lipschitz_violated`) and the same
certified convergence (a sign-change bracket no wider than ``xtol``, adjacent floats, or φ = 0).
A ray's stage is its ``phase`` (march, ladder, refine), as in the array drivers.

The certified methods (``SphereTrace``, and ``MarchRefine`` with a ``CertifiedStep`` rule: their
first-crossing certification, certified MISS and φ's resolution) are not copied here: they run
the array algorithm of :mod:`impls.core.rootfind` with numpy's compacting driver, each φ
evaluation one compiled parallel kernel over the rays (:func:`_run_certified`).  The per-ray
kernels below (``sphere_one``, ``march_one`` with a ``CertifiedStep``, and the hybrid lanes) are
no longer reached for them.

Where the array drivers step every ray still iterating once per loop step (compacting or
masking), this driver runs each ray to completion on its own (``prange`` over rays, threads
``NumbaSettings.threads``), with its state in registers: no per-step overhead, which is what the
array drivers' ladder stage exists to amortise, so the driver's choice for the knob
``ladder = -1`` is no ladder (an explicit ``ladder`` is honoured).  A ray's steps are one chain of
dependent operations, so the hybrid and the constant-step marchers (without derivatives or ladder
steps) run two rays in turn per thread (:mod:`impls.numba.lanes`: the same steps, 1.5× faster
on the speed scenes); the others run one ray at a time (``march_one``, ``sphere_one``).

φ along a ray is the compiled scene (:mod:`impls.numba.fields`); dφ/dt, for Newton, is numpy's
central difference (:mod:`impls.numba.derivatives`), 3 evaluations.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..core.driver import _whole_at_least
from ..core.rootfind import BAD, CONV, IN, LIPV, MAXI, MISS, NONF, Bisect, CertifiedStep, Newton, SphereTrace

#: per-ray ladder samples where the knob leaves it to the driver (-1): none (module docstring)
LADDER = 0


@dataclasses.dataclass(frozen=True)
class NumbaSettings:
    """How the per-ray driver runs, held by the numba backend (``backend.settings``) and recorded
    with every result row (``driver_json``).  Only ``ladder`` changes a per-ray result (it is
    part of the algorithm).

    threads: numba threads running rays side by side (``--threads`` of the bench commands; at
             most ``numba.config.NUMBA_NUM_THREADS``, fixed when numba starts);
    ladder:  samples per ladder step where the knob ``ladder`` is -1 (the driver's choice)."""

    threads: int = 1
    ladder: int = LADDER

    kind = "per-ray"

    def __post_init__(self):
        _whole_at_least(type(self).__name__, "threads", self.threads, 1)
        _whole_at_least(type(self).__name__, "ladder", self.ladder, 0)
        import numba

        most = numba.config.NUMBA_NUM_THREADS
        if self.threads > most:
            raise ValueError(f"{type(self).__name__}: threads={self.threads} exceeds numba's thread pool of {most} "
                             "(NUMBA_NUM_THREADS, set in the environment before numba is imported)")

    def record(self) -> dict:
        """The settings as recorded with a result: ``{"driver": kind, field: value, …, "lanes": rays
        stepped in turn per thread by the lanes kernel}``."""
        from .lanes import LANES

        return {"driver": self.kind, **dataclasses.asdict(self), "lanes": LANES}


# -- the algorithm's numbers, as the kernels take them -------------------------------------------

# float configuration: index names
(F_TMIN, F_TMAX, F_INVLIP, F_TOL, F_OMEGA, F_SCALE, F_LEPS, F_XTOL, F_STEP, F_CHECK, F_MINSTEP, F_CAP, F_EXTRA,
 F_REACH) = range(14)
# int configuration
(I_BOUNDS, I_PROBE, I_MAXSTEPS, I_CERT, I_HASCHECK, I_REFINER, I_LADDER, I_LADDER_AFTER) = range(8)


def _lip_eps(alg, dtype) -> float:
    """16·gain·ε, the Lipschitz check's rounding factor (:func:`impls.core.rootfind.lipschitz_violated`)."""
    return 16.0 * alg.gain * float(np.finfo(np.dtype(dtype)).eps)


def configuration(alg, dtype="float64") -> tuple[str, np.ndarray, np.ndarray]:
    """``(kind, floats, ints)`` of a root finder built by the catalog: ``kind`` "sphere" or
    "march", its numbers in the kernels' layout (index names ``F_*``, ``I_*``)."""
    fc = np.zeros(14)
    ic = np.zeros(8, np.int64)
    fc[F_TMIN], fc[F_TMAX], fc[F_SCALE], fc[F_LEPS] = alg.t_min, alg.t_max, alg.scale, _lip_eps(alg, dtype)
    ic[I_BOUNDS], ic[I_MAXSTEPS] = alg.bounds is not None, alg.max_steps
    if isinstance(alg, SphereTrace):
        fc[F_INVLIP], fc[F_TOL], fc[F_OMEGA] = alg.inv_lip, alg.tol, alg.omega
        ic[I_PROBE] = alg.probe
        return "sphere", fc, ic
    rule, ref = alg.rule, alg.refiner
    fc[F_XTOL] = alg.xtol
    ic[I_LADDER], ic[I_LADDER_AFTER] = alg.ladder, alg.ladder_after
    ic[I_REFINER] = 0 if isinstance(ref, Bisect) else (2 if isinstance(ref, Newton) else 1)
    if isinstance(rule, CertifiedStep):
        ic[I_CERT], ic[I_PROBE] = 1, rule.probe
        fc[F_INVLIP], fc[F_MINSTEP], fc[F_CAP] = rule.inv_lip, rule.min_step, rule.cap
        fc[F_EXTRA], fc[F_REACH] = rule.extrapolate, rule.reach
    else:
        fc[F_STEP] = rule.step
        fc[F_MINSTEP] = rule.min_step
    if rule.check is not None:
        ic[I_HASCHECK], fc[F_CHECK] = 1, rule.check
    return "march", fc, ic


# -- kernels ------------------------------------------------------------------------------------

_KERNELS: dict = {}


def kernels(key: str):
    """``{"march": …, "lanes": …, "phi_rays": …}`` parallel kernels for the scene source ``key``
    (:class:`impls.numba.fields.CompiledScene`), made once per key (the cache lives as long as the
    process); numba compiles each on its first call.  With a cache directory
    (:mod:`impls.cache`) they come from a generated module there (:func:`_cached_module`), whose
    compiled kernels numba keeps on disk between runs."""
    k = _KERNELS.get(key)
    if k is None:
        from ..cache import subdir

        where = subdir("numba")
        if where is not None:
            mod = _cached_module(key, where)
            k = {"march": mod.run_march, "lanes": mod.run_lanes, "phi_rays": mod.phi_rays}
        else:
            from .fields import CompiledScene, scene_functions

            phi, bounds = scene_functions(CompiledScene(key, np.zeros(0)))
            k = _make_kernels(phi, bounds)
        _KERNELS[key] = k
    return k


def kernels_source(key: str) -> str:
    """The source of a module that defines the kernels of :func:`_make_kernels` for the scene
    source ``key`` at its top level, so that numba can cache them on disk (``cache=True`` needs a
    function of a module file, and keys a closure's cache entry on its cell contents, which for
    the jitted functions a closure captures differ in every process).

    The module is put together from the sources themselves, not rewritten: the scene's ``phi``
    and ``bounds`` (``key``), the body of :func:`_make_kernels` (its imports made absolute) and
    the lanes kernel (:func:`impls.numba.lanes.source`); the same algorithm text, compiled the
    same way, with the top-level kernels' caching turned on (``Dispatcher.enable_caching``)."""
    import inspect
    import textwrap

    from . import lanes

    body = inspect.getsource(_make_kernels).split("\n")
    start = next(i for i, ln in enumerate(body) if ln.startswith("def _make_kernels")) + 1
    stop = next(i for i, ln in enumerate(body) if ln.strip() == "from . import lanes")
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
        "from impls.numba.driver import BAD, CONV, IN, LIPV, MAXI, MISS, NONF",
        f"from impls.numba.driver import {consts}",
        "from impls.numba.fields import helpers as _helpers",
        "globals().update({k: v for k, v in _helpers().items() if k not in globals()})",
        "_scene_jit = njit(inline='always', error_model='numpy')",
        "",
        key,
        "phi, bounds = _scene_jit(phi), _scene_jit(bounds)",
        "",
        body,
        "from impls.numba.lanes import CHUNK",
        "",
        lanes.source(),
        "",
        "chunk_lanes_jit = njit(error_model='numpy')(chunk_lanes)",
        "run_lanes = njit(parallel=True, error_model='numpy')(run_lanes)",
        "for _k in (run_march, run_lanes, phi_rays):",
        "    _k.enable_caching()",
        "",
    ])


def _cached_module(key: str, where):
    """The module of :func:`kernels_source` for ``key``, written to ``where`` (once, atomically,
    named by the hash of its text and numba's version) and imported from there."""
    import hashlib
    import importlib.util
    import os

    import numba

    src = kernels_source(key)
    name = "isobench_numba_" + hashlib.sha256((numba.__version__ + "\n" + src).encode()).hexdigest()[:24]
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


def _make_kernels(phi, bounds):
    from numba import njit, prange

    from .derivatives import make_ray_eval
    from .fields import helpers

    h = helpers()
    _max, _min = h["_max"], h["_min"]
    ev, ev_d = make_ray_eval(phi)
    jit = njit(inline="always", error_model="numpy")
    inf, nan = math.inf, math.nan

    @jit
    def lipv(f0, f1, t0, t1, inv_lip, mag, leps):
        """impls.core.rootfind.lipschitz_violated (the inv_lip = 1 branch is this one times 1)."""
        a0, a1 = abs(f0), abs(f1)
        at = (abs(t0) + abs(t1)) + mag
        return abs(f1 - f0) * inv_lip > abs(t1 - t0) + leps * ((a0 + a1) * inv_lip + at)

    @jit
    def verdict(nonf, conv, maxed, miss, lv):
        """impls.core.rootfind._verdict: NON_FINITE, LIPSCHITZ_VIOLATED, MISS, CONVERGED, MAX_ITER."""
        if nonf:
            return NONF
        if lv:
            return LIPV
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

    @njit(error_model="numpy")
    def march_one(p, o0, o1, o2, d0, d1, d2, fc, ic):
        """MarchRefine.init, .step_march, .step_ladder and .step_refine for one ray, with a
        ConstantStep rule (the certified rule runs the core algorithm: :func:`_run_certified`)."""
        t_min, t_max, xtol, leps = fc[F_TMIN], fc[F_TMAX], fc[F_XTOL], fc[F_LEPS]
        has_check, refiner = ic[I_HASCHECK] != 0, ic[I_REFINER]
        max_steps = ic[I_MAXSTEPS]
        ladder, ladder_after = ic[I_LADDER], ic[I_LADDER_AFTER]
        step, check = fc[F_STEP], fc[F_CHECK]
        deriv = refiner == 2
        cost = 3 if deriv else 1
        t, hi, status = start(p, o0, o1, o2, d0, d1, d2, t_min, t_max, ic[I_BOUNDS] != 0)
        if status != IN:
            return final_t(t, status), status, 0, 0
        df = 0.0
        if deriv:
            f, df = ev_d(p, o0, o1, o2, d0, d1, d2, t)
        else:
            f = ev(p, o0, o1, o2, d0, d1, d2, t)
        evals = cost
        if not math.isfinite(f):
            return nan, NONF, 0, evals
        if f == 0:
            return t, CONV, 0, evals
        mag = ((abs(o0) + abs(o1)) + abs(o2)) + fc[F_SCALE]
        p_, fp, a, fa, b = t, f, t, f, t
        wq = inf
        iters = 0
        use_ladder = ladder > 1
        phase = 0
        while True:
            if phase == 0:  # -- step_march --
                t_n = _min(t + step, hi)
                df_n = 0.0
                if deriv:
                    f_n, df_n = ev_d(p, o0, o1, o2, d0, d1, d2, t_n)
                else:
                    f_n = ev(p, o0, o1, o2, d0, d1, d2, t_n)
                zero = f_n == 0
                fin = math.isfinite(f_n)
                cross = fin and (zero or ((f_n > 0) != (f > 0)))
                gone = (t_n >= hi) or not math.isfinite(t_n)
                miss = (not cross) and gone
                conv = cross and (zero or (t_n - t <= xtol))
                nonf = (not fin) and math.isfinite(t_n)
                lv = has_check and lipv(f, f_n, t, t_n, check, mag, leps)
                iters += 1
                evals += cost
                status = verdict(nonf, conv, iters >= max_steps, miss, lv)
                if use_ladder:
                    phase = (1 if (cross or iters >= ladder_after) else 0) + (1 if cross else 0)
                else:
                    phase = 1 if cross else 0
                p_, fp, a, fa, b = t, f, t, f, t_n
                if refiner != 0:
                    wq = 4.0 * (t_n - t)
                t, f, df = t_n, f_n, df_n
            elif phase == 1 and use_ladder:  # -- step_ladder --
                hstep = step
                T, F, DF = np.empty(ladder), np.empty(ladder), np.empty(ladder)  # (rays that reach a ladder only)
                for j in range(ladder):
                    T[j] = _min(t + hstep * float(j + 1), hi)
                    if deriv:
                        F[j], DF[j] = ev_d(p, o0, o1, o2, d0, d1, d2, T[j])
                    else:
                        F[j] = ev(p, o0, o1, o2, d0, d1, d2, T[j])
                e = ladder - 1
                stopped = False
                cross_e = False
                fin_e = True
                lv_e = False
                tp, fpj = t, f
                for j in range(ladder):
                    Tj, Fj = T[j], F[j]
                    crossj = (Fj == 0) or ((Fj > 0) != (fpj > 0))
                    finj = math.isfinite(Fj)
                    event = crossj or not finj
                    lvj = has_check and lipv(fpj, Fj, tp, Tj, check, mag, leps)
                    event = event or lvj
                    if event:
                        e, stopped, cross_e, fin_e, lv_e = j, True, crossj, finj, lvj
                        break
                    tp, fpj = Tj, Fj
                Te, Fe = T[e], F[e]
                Tpe = t if e == 0 else T[e - 1]
                Fpe = f if e == 0 else F[e - 1]
                DFpe = df if e == 0 else DF[e - 1]
                nonf = stopped and (not fin_e) and math.isfinite(Te)
                lv = stopped and lv_e
                onto = cross_e or not stopped
                miss = ((not stopped) and (Te >= hi)) or not math.isfinite(Te)
                conv = cross_e and ((Fe == 0) or (Te - Tpe <= xtol))
                iters += 1
                evals += cost * ladder
                status = verdict(nonf, conv, iters >= max_steps, miss, lv)
                t_new = Te if onto else Tpe
                f_new = Fe if onto else Fpe
                p_, fp, a, fa, b = Tpe, Fpe, Tpe, Fpe, t_new
                phase = (1 if cross_e else 0) + 1
                if refiner != 0:
                    wq = 4.0 * (Te - Tpe)
                if deriv:
                    df = DF[e] if onto else DFpe
                t, f = t_new, f_new
            else:  # -- step_refine --
                mid = 0.5 * (a + b)
                i2 = iters % 3 == 0
                if refiner == 0:
                    c = mid
                else:
                    if refiner == 1:
                        c = t - f * (t - p_) / (f - fp)
                    else:
                        c = t - f / df
                    hh = 0.5 * xtol
                    stp = abs(c - t)
                    lift = stp + 0.5 * hh
                    if stp < hh:
                        c = t + lift if t - a <= b - t else t - lift
                    slow = i2 and (b - a > 0.5 * wq)
                    if not ((c >= a) and (c <= b) and not slow):
                        c = mid
                df_c = 0.0
                if deriv:
                    f_c, df_c = ev_d(p, o0, o1, o2, d0, d1, d2, c)
                else:
                    f_c = ev(p, o0, o1, o2, d0, d1, d2, c)
                same_a = (f_c > 0) == (fa > 0)
                na = c if same_a else a
                nb = b if same_a else c
                nmid = 0.5 * (na + nb)
                conv = (f_c == 0) or (nb - na <= xtol) or (nmid <= na) or (nmid >= nb)
                if refiner == 0:
                    t_out = c
                else:
                    z = c - f_c * (c - t) / (f_c - f)
                    z = _min(_max(z, na), nb)
                    t_out = z if (conv and (f_c != 0) and (z == z)) else c
                iters += 1
                evals += cost
                status = verdict(not math.isfinite(f_c), conv, iters >= max_steps, False, False)
                if refiner != 0 and i2:
                    wq = b - a
                p_, fp = t, f
                a, b = na, nb
                t, f = t_out, f_c
                if deriv:
                    df = df_c
            if status != IN:
                return final_t(t, status), status, iters, evals

    @njit(parallel=True, error_model="numpy")
    def run_march(O, D, p, fc, ic, out_t, out_s, out_i, out_e):
        for i in prange(O.shape[0]):
            t, s, it, ne = march_one(p, O[i, 0], O[i, 1], O[i, 2], D[i, 0], D[i, 1], D[i, 2], fc, ic)
            out_t[i], out_s[i], out_i[i], out_e[i] = t, s, it, ne

    @njit(parallel=True, error_model="numpy")
    def phi_rays(O, D, T, p, F):
        """φ(o_i + t_i d_i) for every ray i: the certified methods' evaluation (:func:`run_loop`)."""
        for i in prange(T.shape[0]):
            F[i] = ev(p, O[i, 0], O[i, 1], O[i, 2], D[i, 0], D[i, 1], D[i, 2], T[i])

    from . import lanes

    ns = {"start": start, "ev": ev, "lipv": lipv, "verdict": verdict, "final_t": final_t, "_max": _max, "_min": _min,
          "math": math, "prange": prange, "inf": inf, "IN": IN, "NONF": NONF, "CONV": CONV, "CHUNK": lanes.CHUNK,
          **{k: v for k, v in globals().items() if k[:2] in ("F_", "I_")}}
    exec(compile(lanes.source(), "<isobench numba lanes>", "exec"), ns)  # noqa: S102 - our own generated source
    ns["chunk_lanes_jit"] = njit(error_model="numpy")(ns["chunk_lanes"])
    run_lanes = njit(parallel=True, error_model="numpy")(ns["run_lanes"])

    return {"march": run_march, "lanes": run_lanes, "phi_rays": phi_rays}


def run_loop(key: str, params: np.ndarray, alg, o: np.ndarray, d: np.ndarray, settings: NumbaSettings) -> dict:
    """Run the catalog's root finder ``alg`` on rays ``o``, ``d`` (float64 (n, 3)) of the compiled
    scene (``key``, ``params``) with ``settings.threads`` threads; ``{t, status, iterations,
    evals}`` (t as reported: ``inf`` for MISS, NaN for NON_FINITE/BAD_INPUT/LIPSCHITZ_VIOLATED)."""
    import numba

    kind, fc, ic = configuration(alg, o.dtype)
    global LAST_COMPILE
    numba.set_num_threads(settings.threads)
    if kind == "sphere" or ic[I_CERT]:
        kernel = kernels(key)["phi_rays"]
        before = compile_state(kernel)
        # compiled here, whether or not these rays evaluate φ (a run's first call compiles: prepare)
        z = np.zeros((1, 3), o.dtype)
        kernel(z, z, np.zeros(1, o.dtype), params, np.empty(1, o.dtype))
        out = _run_certified(kernel, params, alg, o, d)
    else:
        if kind == "march" and ic[I_REFINER] != 2 and ic[I_LADDER] <= 1:
            kind = "lanes"  # (impls.numba.lanes: no derivatives, no ladder stage)
        n = o.shape[0]
        out = {"t": np.empty(n, o.dtype), "status": np.empty(n, np.int32), "iterations": np.empty(n, np.int32),
               "evals": np.empty(n, np.int32)}
        kernel = kernels(key)[kind]
        before = compile_state(kernel)
        kernel(o, d, params, fc, ic, out["t"], out["status"], out["iterations"], out["evals"])
    after = compile_state(kernel)
    LAST_COMPILE = "reused" if before[0] or after[1] > before[1] else "compiled"
    return out


def _run_certified(phi_rays, params: np.ndarray, alg, o: np.ndarray, d: np.ndarray) -> dict:
    """The certified root finders (``SphereTrace``, ``MarchRefine`` with a ``CertifiedStep``
    rule) run by the array algorithm of :mod:`impls.core.rootfind` itself, on numpy arrays with
    the numpy backend's compacting driver, each of its φ evaluations one compiled parallel kernel
    over the rays (``phi_rays``).  Their per-ray certification (the first-crossing check, the
    certified MISS, φ's resolution) is written once, there: a per-ray copy here would be a second
    implementation of it to keep in step."""
    from ..core.driver import CompactingSettings
    from ..numpy.driver import run_loop as run_compacted_numpy

    def ev(oo, dd, t, deriv):
        if deriv:
            raise NotImplementedError("the certified methods evaluate φ only (no dφ/dt)")
        f = np.empty_like(t)
        # (contiguous copies: one compiled specialisation, whatever view the compacting driver passes)
        phi_rays(np.ascontiguousarray(oo), np.ascontiguousarray(dd), np.ascontiguousarray(t), params, f)
        return f, None, 1

    return run_compacted_numpy(alg, o, d, ev, CompactingSettings(threads=1))


#: whether the last :func:`run_loop` call compiled its kernel ("compiled") or found it compiled in
#: this process or on disk ("reused")
LAST_COMPILE: str | None = None
