"""jax backend: ``jax:cpu`` or ``jax:gpu``; every method is jitted, compile time reported apart.

Importing this module turns on ``jax_enable_x64`` (float64 is isobench's truth dtype); arrays
are placed on the backend's device explicitly, so the global default device does not matter.
"""

from __future__ import annotations

import collections
import functools
import time

import jax

jax.config.update("jax_enable_x64", True)


def _persistent_cache() -> bool:
    """Turn on jax's persistent compilation cache in ``<cache dir>/jax`` when the bench commands
    set a cache directory (:mod:`impls.cache`), for every compiled program, however small or
    quick to compile (jax's defaults keep only those that took ≥ 1 s to compile): a harness run
    compiles hundreds of kernels of a fraction of a second to a few seconds each, and pays them
    again on every run otherwise.  Returns whether it is on."""
    from ..cache import subdir

    where = subdir("jax")
    if where is None:
        return False
    jax.config.update("jax_compilation_cache_dir", str(where))
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
    return True


PERSISTENT_CACHE = _persistent_cache()
_cache_hits = [0]


def _count_hits(event: str, **kwargs) -> None:
    if event == "/jax/compilation_cache/cache_hits":
        _cache_hits[0] += 1


jax.monitoring.register_event_listener(_count_hits)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jax import lax  # noqa: E402

from ..base import ArrayBackend  # noqa: E402
from ..protocol import Capabilities  # noqa: E402
from reference.jax_host_call import traced_calls  # noqa: E402
from ..core import rendering  # noqa: E402
from ..core.methods_root import step_field  # noqa: E402
from ..core.rootfind import void_if_refuted  # noqa: E402
from ..core.table import METHOD_TABLE  # noqa: E402
from ..methods import get_method  # noqa: E402
from . import derivatives, driver, executables  # noqa: E402


#: compiled kernels a backend object keeps for reuse (:meth:`JaxBackend.compile_configuration`)
KEEP_KERNELS = 64
#: kernel keys (:meth:`JaxBackend.compile_configuration`: the method, scene, compiled-in knobs and
#: traced knob names, shapes) whose trace failed: that code needs those knobs as constants there.
#: Keyed by the whole configuration, not the method alone, so that one scene's failure (one test's,
#: in a shared process) does not compile the knobs in for every later scene of the method
_TRACED_FAILED: set = set()


#: the depth range [t_min, t_max] as two knobs of a kernel (:meth:`JaxBackend.compile_configuration`)
RANGE_KNOBS = ("t_min", "t_max")
#: the methods whose kernels take the depth range as an argument, not as constants: the root
#: finders, whose code uses it in array arithmetic only (the stability stage's four unit-sphere
#: cases differ in their range alone and share one kernel per method).  Not the volume renderers:
#: they check in Python that the far end is finite (a trace with it traced fails, and would be
#: retried with it compiled in), and no two of the suites' cases give them one scene.
RANGE_METHODS = frozenset(("hybrid_secant", "sphere_trace", "march_bisect", "march_newton", "march_secant",
                           "march_switch"))

#: the constant-step marchers that run as one kernel on the CPU, the refiner an index into this
#: tuple (the knob ``refiner`` of :func:`march_switch`): they differ in their bracket's refinement
#: only, which runs after the search (:func:`impls.jax.driver.run_loop`'s ``later``).  The first
#: searches (bisection's state is the smallest; the secant's bracket width at its last check is
#: made at the hand-off, as its own search makes it on a crossing).  Not Newton's marcher: its
#: search evaluates dφ/dt too, and its refinement keeps the levels (:func:`impls.jax.driver.search_stages`).
REFINER_SWITCH = ("march_bisect", "march_secant")


def march_switch(backend, scene, o, d, *, t_min, t_max, t_hit, refiner, **knobs):
    """The marcher ``REFINER_SWITCH[refiner]`` (``refiner`` an index, traced in a kernel): the
    search of the first of them, then the refinement of the one ``refiner`` picks (``lax.switch``
    in the refinement loop's body).  Each ray's outputs are those of the method itself, bit for
    bit (tests/test_jax_kernel_reuse.py): the searches differ only in the bracket width the secant
    records for its safeguard (:meth:`impls.core.rootfind._OneSided.on_bracket`), made here from
    the bracket at the hand-off instead."""
    scene = step_field(scene)
    algs = [get_method(m).algorithm(scene, t_min, t_max, knobs, None, ladder=backend.settings.ladder)
            for m in REFINER_SWITCH]
    out = backend.run_loop(algs[0], o, d, backend.ray_eval(scene), later=(refiner, algs))
    return void_if_refuted(algs[0], out)


#: the number knobs of the catalog's methods that their code takes as traced values (a loop
#: bound, a tolerance, a step), found by tracing each on its own, and checked jointly and one by
#: one by tests/test_jax_kernel_reuse.py; the others size arrays (samples per ray), switch code
#: paths (bounds, ladder) or enter Python arithmetic (the volume renderers' sharpness).  Tried
#: first for a listed method (:func:`_traced_sets`): a sweep over a listed knob runs one kernel, and
#: no kernel is first traced with knobs that fail.  A method not listed (a user's) gets the generic sets.
TRACEABLE_KNOBS = {
    "hybrid_secant": ("ladder_after", "max_steps", "reach", "xtol") + RANGE_KNOBS,
    "render_surface": ("ladder_after", "max_steps", "reach", "xtol"),
    **{f"march_{m}": ("ladder_after", "max_steps", "step", "xtol") + RANGE_KNOBS
       for m in ("bisect", "newton", "secant")},
    "march_switch": ("ladder_after", "max_steps", "refiner", "step", "xtol") + RANGE_KNOBS,  # (REFINER_SWITCH)
    "sphere_trace": ("max_steps", "omega", "tol") + RANGE_KNOBS,
    "curvature": (), "normal": (),
    # the parts of the volume renderers that fix their bins up front (compile_configuration)
    "volume_samples_band": ("delta",), "volume_samples_stratified": (), "volume_samples_uniform": (),
    **{f"volume_shading_{m}": () for m in ("nerf", "neus", "unisurf", "volsdf")},
    # one kernel for the three density models of SAMPLE_DENSITIES, the model an index (_density_choice)
    "volume_shading_switch": ("density",), "volume_switch_importance": ("density",),
    **{m: ("min_cos",) for m in ("dt_finite_diff", "dt_idr", "dt_implicit")},
    "dt_unrolled": ("min_cos", "steps"),
    # (the stratified sampler's seed is no knob of its kernels: its draws are an input, made at every
    # call from the seed, JaxBackend.compile_configuration — a seed sweep runs one kernel)
    **{f"volume_{m}_{s}": {"band": ("delta",), "stratified": ("seed",)}.get(s, ())
       for m in ("nerf", "neus", "unisurf", "volsdf") for s in ("band", "importance", "stratified", "uniform")},
}


def _traced_sets(method: str, knobs: dict) -> list[tuple[str, ...]]:
    """The knob sets to try as traced arguments of ``method``'s kernel, most first: the method's
    :data:`TRACEABLE_KNOBS` where it has an entry (its other number knobs are known not to trace,
    and trying them would trace the whole kernel once in vain on every compile), else every
    number knob; then the float knobs (tolerances, step sizes; the int knobs are often sizes or
    switches: samples per ray, ladder width, bounds on/off); the first knob (the method's main
    accuracy dial, which a suite sweeps) if it is a float; none.  (A set that failed to trace
    for a configuration is skipped for it and for every configuration that differs only in
    traced knobs: :data:`_TRACED_FAILED`.)"""
    nums = tuple(sorted(k for k, v in knobs.items() if isinstance(v, (int, float)) and not isinstance(v, bool)))
    declared = tuple(k for k in nums if k in TRACEABLE_KNOBS.get(method, ()))
    floats = tuple(sorted(k for k, v in knobs.items() if isinstance(v, float)))
    first = next(iter(knobs), None)
    sets = [declared] if method in TRACEABLE_KNOBS else [nums]
    sets += [floats, (first,) if isinstance(knobs.get(first), float) else (), ()]
    out = []
    for names in sets:
        if names not in out:
            out.append(names)
    return out


def _is_trace_error(exc: BaseException) -> bool:
    """Whether ``exc`` says a traced value was used where the method's code needs a constant (a
    Python branch on it, an array sized by it) — the one failure that sends a knob back to being
    compiled in.  Any other error is the configuration's own and propagates, so that one bad
    configuration cannot stop later kernels of its method from tracing their knobs."""
    trace_errors = tuple(getattr(jax.errors, n) for n in ("ConcretizationTypeError", "TracerArrayConversionError",
                                                           "TracerIntegerConversionError", "TracerBoolConversionError")
                         if hasattr(jax.errors, n))
    return isinstance(exc, trace_errors) or "Tracer" in str(exc) or "concrete" in str(exc)


def _identity(obj):
    """A kernel-table key for an object compiled into a kernel: the object itself where it is
    hashable, else its id (the table keeps the object alive with the kernel).  Colour fields
    compare by value; scene nodes compare by identity (``eq=False``), so a scene built twice is
    traced twice, and its second compilation comes from jax's persistent cache (the same program)."""
    try:
        hash(obj)
    except TypeError:
        return ("id", id(obj))
    return obj


def _devices() -> tuple[str, ...]:
    devs = ["cpu"]
    try:
        if jax.devices("gpu"):
            devs.append("gpu")
    except RuntimeError:
        pass
    return tuple(devs)


class _SavedAtFirstCall:
    """A compiled kernel that, at its first call, hands the call's arguments and outputs to
    ``save(args, outputs=...)`` (:meth:`impls.jax.executables.KernelStore.save`) and then runs as
    the kernel.  The save's cost (serializing, and for a large configuration one run of the
    serialization loaded back) is part of that first call, which a timed run times alone
    (``first_call_s``, bench.run.timing) and an untimed one records as its only call."""

    __slots__ = ("_compiled", "_save")

    def __init__(self, compiled, save):
        self._compiled, self._save = compiled, save

    def __call__(self, *args):
        out = self._compiled(*args)
        save, self._save = self._save, None
        if save is not None:
            save(args, outputs=out)
        return out


def _padded_call(compiled, traced, n: int, rows: int, given: tuple, padded: tuple):
    """``run(o, d, th)`` for a kernel compiled for ``rows`` ≥ n rays: the prepared call's own
    arrays (``given``, the same objects) run as their copies ``padded`` (made once, outside the
    timed call); other arrays are padded per call.  Outputs with ``rows`` leading rows are cut
    back to the first n."""
    def run(o, d, th):
        args = tuple(p if a is g else (None if a is None else driver.pad_rows(a, rows))
                     for a, g, p in zip((o, d, th), given, padded))
        out = compiled(*args, traced)
        return {k: v[:n] if getattr(v, "ndim", 0) and v.shape[0] == rows else v for k, v in out.items()}

    return run


class JaxBackend(ArrayBackend):
    lib = "jax"
    xp = jnp
    settings = driver.MaskedSettings()
    compact = False  # masked blocks: early termination of volume rays is reported, not realised
    stop_gradient = staticmethod(lax.stop_gradient)
    fori_loop = staticmethod(lax.fori_loop)  # a long unroll does not become a long trace
    switch = staticmethod(lax.switch)  # a traced index: one kernel for the models it picks among

    def __init__(self, device: str = "cpu", settings: driver.MaskedSettings | None = None):
        # compile_configuration's kernels, one per structure, the least recently used dropped past
        # KEEP_KERNELS (a catalog sweep compiles thousands; a run plans a case's configurations together)
        self._kernels: collections.OrderedDict = collections.OrderedDict()
        self.capabilities = Capabilities(
            dtypes=("float64", "float32"),
            devices=_devices(),
            autodiff="both",
            jit=True,
            notes=("methods run under jax.jit; fixed-shape masked loops: lax.map over chunks of rays, each "
                   "compacted level by level into smaller batches, one lax.while_loop per stage and level (a root "
                   "finder's refinement and certification stages, but Newton's, once per chunk after the levels); the "
                   "chunks' stragglers after a capped number of steps of the last level finished together; n rays "
                   "run as the next power of two ≥ max(n, settings.pad) rows, copies of the first ray, whose "
                   "outputs are dropped (sizes: backend.settings, recorded with every result)",
                   "render_surface runs two kernels: hybrid_secant's own (compiled once for both methods) and one "
                   "that shades its hit; on the CPU the volume renderers with the uniform, stratified and band "
                   "samplers run the sampler's kernel and the density model's shading kernel (one per model for the "
                   "three samplers); a time is the two calls",
                   "on the CPU one kernel serves several methods where they differ in one choice, taken as a runtime "
                   "index (lax.switch): the nerf, volsdf and unisurf renderers (the density model; neus has its own), "
                   "march_bisect and march_secant (the refiner, after bisection's search); each method's outputs are "
                   "those of a kernel of its own, bit for bit",),
            expected_failures=(
                ("eval_count", "masked loops evaluate φ on every ray of a chunk each iteration (and jit traces φ "
                 "once), so counted calls ≠ per-ray evals; evals counts the evaluations a ray used"),
            ),
        )
        super().__init__(device, settings)
        self.jax_device = jax.devices(device)[0]
        # kernels on disk by what they compute, found without tracing (None without a cache directory)
        self._store = executables.default_store()
        self._cached_bytes = None  # (_compile_traced)

    def asarray(self, a, dtype):
        return jax.device_put(jnp.asarray(np.asarray(a), dtype=dtype), self.jax_device)

    def to_numpy(self, a):
        return np.asarray(a)

    def synchronize(self, out=None):
        if out is not None:
            jax.block_until_ready(out)
        else:
            (jax.device_put(0.0, self.jax_device) + 0).block_until_ready()

    def compile(self, fn, *example_args):
        """``jax.jit(fn)`` lowered and compiled for ``example_args``: (compiled, seconds).  Whether
        the executable came from the persistent cache is left in ``last_compile_cache``
        ("reused" or "compiled"; None without a cache directory)."""
        t0 = time.perf_counter()
        compiled = self._compile_traced(jax.jit(fn).trace(*example_args))
        return compiled, time.perf_counter() - t0

    def _compile_traced(self, traced):
        """A traced kernel lowered and compiled (or loaded from jax's persistent cache); sets
        ``last_compile_cache``, and ``_cached_bytes`` to the serialized executable jax read from its
        persistent cache where it loaded it from there (else None: compiled here)."""
        hits = _cache_hits[0]
        with executables.persistent_cache_reads() as reads:
            compiled = traced.lower().compile()
        hit = _cache_hits[0] > hits
        self.last_compile_cache = None if not PERSISTENT_CACHE else ("reused" if hit else "compiled")
        self._cached_bytes = reads[0] if hit and len(reads) == 1 else None
        return compiled

    def compile_configuration(self, call, knobs, o, d, th, *, method, scene, t_range, extra):
        """:meth:`_compile_configuration`; for the stratified volume renderers (``draws_jitter``,
        :func:`impls.core.rendering.make_volume_sampler`) the sampler's offsets are an input of the
        kernel, drawn on the host at every call (:func:`impls.core.rendering.stratified_jitter`, the
        draws numpy and torch make inside theirs), not constants compiled into it, which made every
        such kernel as large as its draws (rays × samples floats) in XLA's compile and in both
        caches (figures: docs/performance.md).  The seed is then no part of the kernel."""
        impl = self._impl.get(method)
        if th is not None or not getattr(impl, "draws_jitter", False) or "seed" not in knobs:
            return self._compile_configuration(call, knobs, o, d, th, method=method, scene=scene, t_range=t_range,
                                               extra=extra)
        seed, knobs = knobs["seed"], {k: v for k, v in knobs.items() if k != "seed"}
        rows, n_samples = driver.padded_size(o.shape[0], self.settings.pad), knobs["n_samples"]  # padding rows too
        dtype, device = o.dtype, self.jax_device

        def draw(first=0, count=rows):  # the offsets of rows first … first + count − 1
            return jax.device_put(np.asarray(rendering.stratified_jitter(seed, count, n_samples, first), dtype), device)

        t_min, t_max = t_range

        def jittered(o, d, u, knobs):
            return impl(self, scene, o, d, t_min=t_min, t_max=t_max, t_hit=None, jitter=u, **extra, **knobs)

        return self._compile_configuration(jittered, knobs, o, d, None, method=method, scene=scene, t_range=t_range,
                                           extra=extra, jitter=draw)

    def _compile_configuration(self, call, knobs, o, d, th, *, method, scene, t_range, extra, jitter=None):
        """One kernel per structure: the knobs are traced arguments of the jitted function where the
        method's code allows it (:func:`_traced_sets`), so configurations that differ only in
        those knobs run one compiled kernel (the backend object keeps the last ``KEEP_KERNELS``).
        The kernel is keyed by everything compiled into it: the method, the scene and colour
        objects (their parameters are constants of the kernel), the depth range (two knobs,
        ``t_min`` and ``t_max``, of the root finders: :data:`RANGE_METHODS`), the knobs compiled in,
        the driver settings and the rays' shapes and dtype.  A kernel not in the table is looked up
        in the cache directory's kernel store by the same inputs taken by value
        (:mod:`impls.jax.executables`: no trace, no lowering), and else traced, lowered and compiled
        (or loaded from jax's persistent cache) and stored.  ``last_compile_cache``: "reused" when
        the kernel came from this table, the kernel store or the persistent cache, "compiled"
        otherwise (None without a cache directory and nothing to reuse).  A traced knob is a weakly typed scalar,
        so it enters float32 arithmetic as the Python constant it replaces does.  The rays run as
        ``driver.padded_size(n, settings.pad)`` rows (copies of the first ray appended, padded once
        here, their outputs dropped), so that ray sets of nearby sizes share a kernel.

        A method whose implementation comes in two parts runs as two kernels, the second given the
        first's outputs (nothing fuses across a root finder's loops), and the first is shared:

        * ``hit_method`` (``render_surface``, the hit of ``hybrid_secant``): that root method's
          kernel, the very one its own configurations run, then one that shades its hit
          (:func:`impls.core.rendering.render_surface`'s ``hit``);
        * ``stages`` (the volume renderers whose bins are fixed up front,
          :func:`impls.core.rendering.make_volume_impl`), on the CPU: the sampler's kernel (it
          does not read the scene), then the density model's shading, one kernel for the uniform,
          stratified and band samplers; for more rays than a block (memory:
          :func:`impls.core.rendering.shading_rows`) both compiled for a block and run block by
          block.  Not on a GPU: there a second call's dispatch is as long as such a kernel's work
          (docs/performance.md); a root finder's loops are not.

        One kernel serves several methods that differ in one choice, a traced index, on the CPU:

        * the volume renderers of the density models nerf, volsdf and unisurf
          (:data:`impls.core.rendering.SAMPLE_DENSITIES`, :meth:`_density_choice`): one shading
          kernel (``volume_shading_switch``) and one importance-sampling kernel
          (``volume_switch_importance``) for the three;
        * ``march_bisect`` and ``march_secant`` (:data:`REFINER_SWITCH`, :meth:`_refiner_choice`):
          one ``march_switch`` kernel, bisection's search, then the refiner the index picks.

        ``jitter``: ``draw(first=0, count=all padded rows)``, the stratified sampler's offsets of
        those rows (:meth:`compile_configuration`), drawn at every call and given to the kernel as
        its ``th`` (the sampler takes them as its ``jitter``, not as a hit); ``th`` is then None."""
        n = o.shape[0]
        rows = driver.padded_size(n, self.settings.pad)
        given = (o, d, th)
        padded = tuple(None if a is None else driver.pad_rows(a, rows) for a in given)
        impl = self._impl.get(method)
        hit_method, stages = getattr(impl, "hit_method", None), getattr(impl, "stages", None)
        t_min, t_max = t_range
        choice = self._density_choice(method, impl)
        if hit_method is not None and th is None and hit_method in self._impl:
            root = self._impl[hit_method]
            # what the hit method's own configurations run (the same kernel)
            hit_call, hit_knobs, hit_range = self._ranged(root, hit_method, scene, {}, knobs, t_range)
            first = dict(call=hit_call, knobs=hit_knobs, method=hit_method, impl=root, scene=scene, extra={},
                         t_range=hit_range)
            second = dict(call=lambda o, d, hit, knobs: call(o, d, None, {**knobs, "hit": hit}), knobs=knobs,
                          method=method, impl=impl, scene=scene, extra=extra)
            return self._compile_chain(first, second, n, rows, given, padded, t_range)
        if stages is not None and set(extra) <= {"color"} and self.jax_device.platform == "cpu":
            sample, shade = stages
            shade_knobs = {k: v for k, v in knobs.items() if k in shade.knobs}
            sample_knobs = {k: v for k, v in knobs.items() if k not in shade.knobs}
            if choice is not None:  # the shading of the three models: one kernel
                shade, shade_knobs = rendering.SWITCH_SHADING, {**shade_knobs, "density": choice}

            def sample_call(o, d, th, knobs):
                given = {"t_hit": None, "jitter": th} if jitter else {"t_hit": th}  # th: the offsets (above)
                return sample(self, None, o, d, t_min=t_min, t_max=t_max, **given, **knobs)

            def shade_call(o, d, samples, knobs):
                return shade(self, scene, o, d, samples=samples, **extra, **knobs)

            first = dict(call=sample_call, knobs=sample_knobs, method=sample.__name__, impl=sample, scene=None,
                         extra={})
            second = dict(call=shade_call, knobs=shade_knobs, method=shade.__name__, impl=shade, scene=scene,
                          extra=extra)
            return self._compile_chain(first, second, n, rows, given, padded, t_range,
                                       block=rendering.shading_rows(shade.model, knobs["n_samples"]), draw=jitter)
        if choice is not None and rendering.DENSITY_CHOICES[method][1] == "importance":  # the three models: one kernel
            impl = rendering.SWITCHED["importance"]
            method, knobs, call = impl.__name__, {**knobs, "density": choice}, None
        refiner = self._refiner_choice(method, impl, th)
        if refiner is not None:  # the marchers of REFINER_SWITCH: one kernel
            impl, method, knobs, call = march_switch, "march_switch", {**knobs, "refiner": refiner}, None
        if impl is not None:
            call, knobs, t_range = self._ranged(impl, method, scene, extra, knobs, t_range, call)
        if jitter is not None:  # the offsets of all rows, drawn at every call
            padded = padded[:2] + (jitter(),)
        compiled, traced, spent = self._kernel(call, knobs, *padded, method=method, scene=scene, t_range=t_range,
                                               extra=extra, impl=impl)
        if jitter is not None:
            run = _padded_call(compiled, traced, n, rows, given, padded)
            return (lambda o, d, th: run(o, d, jitter())), spent
        if rows == n:
            return (lambda o, d, th: compiled(o, d, th, traced)), spent
        return _padded_call(compiled, traced, n, rows, given, padded), spent

    def _density_choice(self, method, impl) -> int | None:
        """For a catalog volume renderer of a density model of
        :data:`impls.core.rendering.SAMPLE_DENSITIES` on the CPU: the model's index there, the knob
        ``density`` of the kernel that runs the three models (:class:`impls.core.rendering.DensityChoice`,
        ``lax.switch`` on a traced index: one compilation instead of three, the same bits and run
        times, docs/performance.md), else None.  Not on a GPU, where a conditional's cost has not
        been measured (no device was at hand), and not for a renderer a caller put in the table."""
        if (self.jax_device.platform != "cpu" or method not in rendering.DENSITY_CHOICES
                or impl is not rendering.IMPLS.get(method)):
            return None
        return rendering.DENSITY_CHOICES[method][0]

    def _refiner_choice(self, method, impl, th) -> int | None:
        """For a marcher of :data:`REFINER_SWITCH` from the catalog, on the CPU, with its
        refinement after the levels (``settings.park``): its index there, the knob ``refiner`` of
        :func:`march_switch`'s kernel, which runs them all (one compilation instead of two; the
        same bits and run times: docs/performance.md), else None.  Not on a GPU (as
        :meth:`_density_choice`), not for a method a caller put in the table."""
        if (method not in REFINER_SWITCH or th is not None or self.jax_device.platform != "cpu"
                or not self.settings.park or impl is None or impl is not METHOD_TABLE.get(method)):
            return None
        return REFINER_SWITCH.index(method)

    def _ranged(self, impl, method, scene, extra, knobs, t_range, call=None):
        """``(call, knobs, t_range)`` for :meth:`_kernel`: for a method of :data:`RANGE_METHODS`,
        a call of ``impl`` that takes the depth range from the knobs ``t_min`` and ``t_max`` (so
        that they may be traced), the knobs with the range added, and no range of its own for the
        key (it is in the knobs); else ``call`` (or ``impl`` bound to ``t_range``) as given."""
        t_min, t_max = t_range
        if method not in RANGE_METHODS:
            if call is None:
                def call(o, d, th, knobs):
                    return impl(self, scene, o, d, t_min=t_min, t_max=t_max, t_hit=th, **extra, **knobs)
            return call, knobs, t_range

        def ranged(o, d, th, knobs):
            knobs = dict(knobs)
            lo, hi = knobs.pop("t_min"), knobs.pop("t_max")
            return impl(self, scene, o, d, t_min=lo, t_max=hi, t_hit=th, **extra, **knobs)

        return ranged, {**knobs, "t_min": t_min, "t_max": t_max}, None

    def _compile_chain(self, first: dict, second: dict, n, rows, given, padded, t_range, block=None, draw=None):
        """``run(o, d, th)`` as two kernels (:meth:`compile_configuration`): ``first["call"](o, d,
        th, knobs)``, then ``second["call"](o, d, out, knobs)`` given the first's output ``out``;
        ``last_compile_cache`` "reused" when both were.  ``block``: where the padded rows are
        more, and a multiple of it, the two kernels are compiled for ``block`` rows and run block
        by block in a loop here, so that what the first hands the second (a volume renderer's
        bins: rays × samples) is a block's, not the camera's (the rays of every camera larger
        than a block then share the kernels).  ``draw``: ``draw(first, count)`` gives the first
        kernel's ``th`` of those rows at every call (the stratified draws, a block's at a time)."""
        per = block if block is not None and rows > block and rows % block == 0 else rows

        def part(a, i):  # rows i … i + per of an input (None, an array or a dict of arrays); all: itself
            return a if per == rows else jax.tree.map(lambda x: x[i:i + per], a)

        def th_part(th, i):
            return part(th, i) if draw is None else draw(i, per)

        o, d, th = part(padded[0], 0), part(padded[1], 0), th_part(padded[2], 0)
        k1, traced1, spent = self._kernel(first["call"], first["knobs"], o, d, th, method=first["method"],
                                          impl=first["impl"], scene=first["scene"],
                                          t_range=first.get("t_range", t_range), extra=first["extra"])
        reused = self.last_compile_cache == "reused"
        t0 = time.perf_counter()
        example = k1(o, d, th, traced1)  # the second kernel's example input
        spent += time.perf_counter() - t0
        k2, traced2, more = self._kernel(second["call"], second["knobs"], o, d, example, method=second["method"],
                                         impl=second["impl"], scene=second["scene"], t_range=t_range,
                                         extra=second["extra"])
        if self.last_compile_cache is not None:
            self.last_compile_cache = "reused" if reused and self.last_compile_cache == "reused" else "compiled"

        def chained(o, d, th, _):
            if per == rows:
                return k2(o, d, k1(o, d, th_part(th, 0), traced1), traced2)
            parts = []
            for i in range(0, rows, per):
                ob, db = o[i:i + per], d[i:i + per]
                parts.append(k2(ob, db, k1(ob, db, th_part(th, i), traced1), traced2))
            return jax.tree.map(lambda *xs: jnp.concatenate(xs), *parts)

        if rows == n:
            return (lambda o, d, th: chained(o, d, th, None)), spent + more
        return _padded_call(chained, None, n, rows, given, padded), spent + more

    def _kernel(self, call, knobs, o, d, th, *, method, scene, t_range, extra, impl=None):
        """``(compiled, traced knob values, seconds spent)`` of ``call(o, d, th, knobs)`` on rays
        already padded (:meth:`compile_configuration`); ``th``: None, an array or a dict of arrays;
        ``impl``: the function ``call`` runs, where it is not the method's own (the store's key
        checks whose code it is)."""
        spent = 0.0
        for names in _traced_sets(method, knobs):
            names = tuple(k for k in names if k in knobs)  # a part of a method takes part of its knobs
            static = {k: v for k, v in knobs.items() if k not in names}
            key = (method, _identity(scene), t_range, tuple(sorted((k, _identity(v)) for k, v in extra.items())),
                   tuple(sorted(static.items())), names, self.device, self.settings,
                   *(executables.array_layout(a) for a in (o, d, th)))
            if names and key in _TRACED_FAILED:
                continue
            t0 = time.perf_counter()
            kept = self._kernels.get(key)
            if kept is not None:
                self._kernels.move_to_end(key)
                self.last_compile_cache = "reused"
            else:

                def fn(o, d, th, traced, static=static):
                    return call(o, d, th, {**static, **traced})

                traced = {k: knobs[k] for k in names}
                stored = None if self._store is None else executables.kernel_key(
                    self, method, scene, t_range, extra, static, traced, (o, d, th), impl=impl)
                compiled = None if stored is None else self._store.load(stored, self.jax_device)
                if compiled is not None:
                    self.last_compile_cache = "reused"
                else:
                    host_calls = traced_calls()
                    try:
                        trace = jax.jit(fn).trace(o, d, th, traced)
                    except (TypeError, ValueError) as exc:
                        if not names or not _is_trace_error(exc):
                            raise  # a fault of the scene or the knobs, not of tracing them
                        # the method's code branches on (or sizes arrays by) one of these knobs:
                        # compile them in, for this configuration and its sweeps from now on
                        _TRACED_FAILED.add(key)
                        spent += time.perf_counter() - t0
                        continue
                    # jax's persistent cache writes its own copy too: keyed by the program, it still
                    # answers after an edit of isobench changed every store key (docs/performance.md)
                    compiled = self._compile_traced(trace)
                    # stored: a kernel XLA compiled here, or one jax loaded from its persistent cache
                    # whose bytes it read are at hand (its own serialization does not run:
                    # impls.jax.executables), without a call back into Python (a mesh's φ: its
                    # trace registers the call's target) — at the kernel's first call, whose outputs
                    # are the ones the entry is checked against (computing them here was one more
                    # run of every kernel a cold run compiled)
                    cached = self._cached_bytes  # (None where XLA compiled it here)
                    if (stored is not None and traced_calls() == host_calls
                            and (self.last_compile_cache != "reused" or cached is not None)):
                        compiled = _SavedAtFirstCall(compiled, functools.partial(
                            self._store.save, stored, compiled, device=self.jax_device, executable_bytes=cached))
                # the scene and colour objects are kept alive with the kernel: their ids are in the key
                self._kernels[key] = kept = (compiled, scene, extra)
                while len(self._kernels) > KEEP_KERNELS:
                    self._kernels.popitem(last=False)
            return kept[0], {k: knobs[k] for k in names}, spent + time.perf_counter() - t0
        raise AssertionError("unreachable: the last set of traced knobs is empty")  # pragma: no cover

    def map_rays(self, fn, arrays, rows):
        """:meth:`impls.base.ArrayBackend.map_rays` inside a kernel: the rays (padded with copies of
        the first up to a multiple of ``rows``) as ``lax.map`` over blocks of ``rows``, one block's
        arrays live at a time; a batch of at most ``rows`` rays is ``fn`` itself (the same program
        as without blocks)."""
        n = next(a.shape[0] for a in arrays if a is not None)
        if n <= rows:
            return fn(*arrays)
        k = -(-n // rows)

        def split(a):
            return None if a is None else driver.pad_rows(a, k * rows).reshape((k, rows) + a.shape[1:])

        out = lax.map(lambda xs: fn(*xs), tuple(split(a) for a in arrays))
        return jax.tree_util.tree_map(lambda a: a.reshape((k * rows,) + a.shape[2:])[:n], out)

    def untimed_settings(self) -> dict:
        """Driver settings for a run that times nothing (the stability stage, ``--accuracy-only``;
        :func:`bench.run.environment.untimed_backend`): one compaction level per chunk
        (``last = chunk``).  The levels exist for run time only: a ray's results do not depend on
        them (``tests/test_driver.py``), and each level is a copy of every stage's loop, φ inlined,
        in the compiled program (compile times: docs/performance.md)."""
        return {"last": self.settings.chunk}

    def versions(self):
        import jaxlib

        return {"jax": jax.__version__, "jaxlib": jaxlib.__version__}

    def ray_eval(self, scene, theta=None):
        return derivatives.ray_eval(scene, theta)

    def grad_hess(self, scene, x, hess, theta=None):
        return derivatives.grad_hess(scene, x, hess, theta)

    def theta_jacobian(self, fun, theta):
        return derivatives.theta_jacobian(fun, theta)

    def run_loop(self, alg, o, d, ev, later=None):
        """:func:`impls.jax.driver.run_loop` with this backend's settings; ``later``: its argument
        (another algorithm's later stages after ``alg``'s search: :func:`march_switch`)."""
        st = self.settings
        return driver.run_loop(alg, o, d, ev, chunk=st.chunk, ratio=st.ratio, last=driver.smallest_level(alg, st),
                               tail_cap=st.tail_cap, park=bool(st.park), later=later)
