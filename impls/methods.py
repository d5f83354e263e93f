"""The method catalog: names, knobs (the accuracy dials bench sweeps), and scene requirements.

One table shared by every backend, by the planner (which skips a method whose requirement the
scene does not meet, with the reason) and by the conformance tests.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from typing import Any, Callable

import numpy as np

from .core import methods_root


#: what a knob does, which decides how a suite sweeps it (``bench/run/suites.py``, ``default_sweep``)
KNOB_ROLES = {
    "tolerance": "a stopping tolerance (float): swept over decades; the tightest swept value is held while a "
                 "budget sweeps",
    "budget": "a count of steps, iterations or samples (int): swept geometrically up to its default",
    "step": "a step length or resolution (float): held at its default unless a suite names values",
    "seed": "a random seed (int): never swept",
    "setting": "an algorithm or model setting (a switch, a relaxation factor, a sharpness): never swept",
}


@dataclasses.dataclass(frozen=True)
class Knob:
    """One accuracy or behaviour dial of a method.

    ``low``/``high`` are inclusive validity bounds (``check`` rejects values outside them);
    ``role`` is one of :data:`KNOB_ROLES`, declared by the method's author: suites sweep a knob by
    its role, never by its name; ``sweep`` (optional) names the values to sweep instead."""

    name: str
    default: Any
    kind: type
    low: float  # inclusive lower bound
    doc: str
    high: float = math.inf  # inclusive upper bound
    role: str = dataclasses.field(default="", kw_only=True)
    #: values a suite sweeps this knob over whatever its role (None: by its role)
    sweep: tuple | None = dataclasses.field(default=None, kw_only=True)

    def __post_init__(self):
        if self.role not in KNOB_ROLES:
            raise ValueError(f"Knob {self.name!r}: role={self.role!r} must be one of {sorted(KNOB_ROLES)} "
                             "(how a suite sweeps it); pass e.g. Knob(..., role='tolerance')")

    #: int knobs are step/sample counts held in int32 counters
    INT_MAX = 2**31 - 1

    def valid_range(self) -> str:
        hi = min(self.high, self.INT_MAX) if self.kind is int else self.high
        what = "an integer" if self.kind is int else "a finite real number"
        fmt = (lambda v: str(int(v))) if self.kind is int else (lambda v: f"{v:g}")  # noqa: E731
        return f"{what} ≥ {fmt(self.low)}" if hi == math.inf else f"{what} in [{fmt(self.low)}, {fmt(hi)}]"

    def check(self, method: str, value: Any) -> Any:
        """``value`` as this knob's kind, or an error naming the method, the knob and its valid range.

        TypeError: not a real number (a string, None, an array, or a bool: ``True`` is not 1 step).
        ValueError: NaN or ±inf, a non-integral value for an integer knob, or outside [low, high]."""
        where = f"{method}: knob {self.name}={value!r}"
        valid = f"valid: {self.valid_range()} ({self.doc})"
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
            raise TypeError(f"{where} must be a number, not {type(value).__name__}; {valid}")
        if self.kind is int:
            if isinstance(value, numbers.Integral):
                v = int(value)
            else:
                f = float(value)
                if not math.isfinite(f):
                    raise ValueError(f"{where} must be finite; {valid}")
                if f != int(f):
                    raise ValueError(f"{where} must be an integer; {valid}")
                v = int(f)
            hi = min(self.high, self.INT_MAX)
        else:
            v = float(value)
            if not math.isfinite(v):
                raise ValueError(f"{where} must be finite; {valid}")
            hi = self.high
        if not (self.low <= v <= hi):
            raise ValueError(f"{where} is out of range; {valid}")
        return v


@dataclasses.dataclass(frozen=True)
class MethodSpec:
    """A method's contract.

    family:   ``root`` (finds t), ``gradient`` (normals/curvature at given hits), ``param_grad``
              (dt/dθ at given hits), ``render`` (colour per ray); bench measures each family's
              error against the matching reference answer.
    requires: :class:`reference.SceneInfo` fields that must be truthy for the method to apply
              (e.g. ``lipschitz`` for sphere tracing).
    needs_t_hit: the method evaluates at given per-ray depths (``prepare(..., t_hit=...)``).
    outputs:  names of the extra per-ray outputs in :attr:`RayResult.outputs`.
    needs_color: the method shades with a colour field ρ (``prepare(..., color=field)``, a field
              with ``value(x, xp) -> (..., 3)``; default :class:`reference.rendering.SineColor`).
              A runner passes ``color=case.color_field`` exactly when this is true; ``prepare``
              rejects ``color`` for a method without it.
    finite_range: the method samples the whole interval [t_min, t_max] (volume rendering), so
              ``prepare`` refuses t_max = inf (a ValueError naming it) and the runner plans no such
              configuration (skipped, with the reason) on a case whose t_max is infinite.
    """

    name: str
    family: str
    knobs: tuple[Knob, ...]
    requires: tuple[str, ...]
    description: str
    needs_t_hit: bool = False
    outputs: tuple[str, ...] = ()
    needs_color: bool = False
    finite_range: bool = False
    #: root family: ``build(scene, t_min, t_max, knobs, theta, *, ladder)`` → the algorithm
    #: (:mod:`impls.core.rootfind`) from the knobs ``validate`` returned; ``ladder`` is the loop
    #: driver's choice of ladder samples for the knob value -1 (:mod:`impls.core.methods_root`)
    build: Callable[..., Any] | None = None
    #: array libraries (``Backend.lib``) whose backends offer the method; None: every backend.  A
    #: built-in backend of another library leaves it out of ``methods()``, and the runner records
    #: such a configuration as skipped ("does not implement")
    libs: tuple[str, ...] | None = None
    #: the dtypes the method computes in whatever a run asks (an engine's own precision); the planner
    #: plans it in these (in those of them ``--dtype`` names, when it names any); None: the run's dtypes
    dtypes: tuple[str, ...] | None = None

    def algorithm(self, scene, t_min: float, t_max: float, knobs: dict[str, Any], theta: Any = None, *,
                  ladder: int) -> Any:
        """The root finder of this method for ``knobs`` as :meth:`validate` returns them (every knob
        present: defaults are filled there, once)."""
        if self.build is None:
            raise ValueError(f"{self.name} is a {self.family} method, not a root finder")
        return self.build(scene, t_min, t_max, knobs, theta, ladder=ladder)

    def skip_reason(self, scene) -> str | None:
        info = scene.info
        missing = [r for r in self.requires if not getattr(info, r)]
        if missing:
            return f"{self.name} needs a scene with {', '.join(missing)}; {type(scene).__name__} states none"
        if self.family == "param_grad":
            params = getattr(scene, "param_vector", None)
            if not callable(params) or np.asarray(params()).size == 0:
                return (f"{self.name} differentiates hits by the scene's parameters θ and {type(scene).__name__} has "
                        "none (param_vector() is empty); a user's field takes them as CallableField(fn, ..., "
                        "params=θ), called fn(x, xp, theta)")
        return None

    def validate(self, knobs: dict[str, Any]) -> dict[str, Any]:
        names = {k.name for k in self.knobs}
        unknown = set(knobs) - names
        if unknown:
            raise ValueError(f"{self.name}: unknown knob(s) {sorted(map(str, unknown))}; valid knobs are "
                             f"{sorted(names) or 'none'}")
        return {k.name: k.check(self.name, knobs.get(k.name, k.default)) for k in self.knobs}


# -- the catalog --------------------------------------------------------------------------------
# Knob bounds are validity bounds (prepare rejects values outside them); defaults are the
# "good" setting.  The first knob of each method is its main accuracy dial.

_MAX_STEPS = Knob("max_steps", 512, int, 1, "step budget per ray (MAX_ITER when spent)", role="budget")
# the hybrids and the marches certify their bracket against φ's rounding, so their default is one
# float64 certifies on the catalog's meshes: φ's modelled rounding on mesh.fin (rounding gain 400) is ~4e-12 at its depths,
# and the stretch where its sign is rounding, 2·rounding/σ at slope σ, exceeds 1e-12 on a quarter of
# its 1024² camera's hits (sphere_trace's default tol is 1e-10 likewise).  The marches' was 1e-12 until
# they verified their brackets too (2026-11-30): at 1e-12, 82,687 of that camera's 304,387 hits were then
# UNCERTIFIED (march_secant), at 1e-10 13,442, the statuses of before, depths within 8e-14 either way
_CERT_XTOL = Knob("xtol", 1e-10, float, 0.0, "converged when the bracket of resolved signs of φ (|φ|/L beyond φ's "
                  "modelled rounding) around the crossing is ≤ max(xtol, 4 roundings, 2 float spacings) wide "
                  "(depth units; the depth found is usually far closer)", role="tolerance")
_MIN_STEP = Knob("min_step", 1e-4, float, 1e-9,
                 "first-crossing tolerance: a CONVERGED depth is within min_step + xtol of the first crossing (a pair "
                 "of crossings with chord < min_step just before it can be passed over); a step this short may stand "
                 "uncertified on a nearly tangent ray, whose answer is then UNCERTIFIED", role="step")
_OVERSTEP = Knob("overstep", 0.0, float, 0.0,
                 "largest forced step Δ beyond |φ|/L, halved down to min_step while a step is not certified "
                 "(≤ min_step, the default: no forced steps beyond min_step, the plain IDR march)", role="step")
_BOUNDS = Knob("bounds", 1, int, 0, "1: search only inside the scene's ray bounds (Field.ray_bounds: bounding "
               "spheres, boxes, a union's hull; rays outside them are MISS at once); 0: all of [t_min, t_max]", 1, role="setting")
_HYBRID_MAX_STEPS = Knob("max_steps", 4096, int, 1, "budget of marching plus refinement steps (MAX_ITER when spent)", role="budget")
_LADDER = Knob("ladder", -1, int, -1, "a ray still marching after ladder_after steps goes on in ladder steps: this "
               "many marching samples evaluated together, judged pair by pair as single steps, each a step against "
               "max_steps (0 or 1: off; -1: the backend's loop driver chooses: 16 on the compacting numpy/torch/Warp "
               "drivers, off on jax's masked loops and numba's per-ray loops; a hybrid goes on in ladder steps only "
               "once past the frontier of its certified stretch by min_step, where no answer can be certified any "
               "more, so that its ladder changes no certified answer)",
               4096, role="setting")
_LADDER_AFTER = Knob("ladder_after", 64, int, 0, "marching steps before a ray goes on in ladder steps", role="setting")
_EXTRAPOLATE = Knob("extrapolate", 1.05, float, 0.0, "over-relaxed steps (2|φ|/L/(1 + σ), σ the secant's slope) "
                    "and a crossing step of this × the secant's distance to its zero, within reach, once the stretch "
                    "it leaves uncertified is predicted under min_step (0: off, plain steps max(|φ|/L, Δ))", role="setting")
_REACH = Knob("reach", 0.1, float, 0.0, "largest extrapolated step (depth units; a step not certified is rejected, "
              "so this bounds what a rejection wastes, not what can be missed)", role="step")
_MIN_COS = Knob("min_cos", 1e-6, float, 0.0, "ILL_CONDITIONED when |⟨∇φ, d⟩|/|∇φ| < min_cos (grazing)", 1.0, role="setting")
_REFINE_DOC = {
    "bisect": "bisection (linear, ratio 1/2)",
    "secant": "safeguarded secant (order ≈ 1.618)",
    "newton": "safeguarded Newton with φ' = ⟨∇φ, d⟩ (order 2; autodiff, or central differences in numpy)",
    "chandrupatla": "scipy.optimize.elementwise.find_root (Chandrupatla: inverse quadratic interpolation or "
                    "bisection), CONVERGED only on a certified bracket (numpy backend only)",
}
#: refiners that run outside the backends' loop drivers, and the libraries that offer them
_REFINE_LIBS = {"chandrupatla": ("numpy",)}
DENSITIES = {
    "nerf": "NeRF-style density σ = s·sigmoid(−sφ) from the field, α = 1 − exp(−σδ)",
    "unisurf": "UNISURF occupancy as alpha, α = sigmoid(−sφ) at each sample",
    "neus": "NeuS discrete opacity α = max((Φ_s(φ_i) − Φ_s(φ_{i+1}))/Φ_s(φ_i), 0), Φ_s = sigmoid(s·)",
    "volsdf": "VolSDF Laplace density σ = s·Ψ(−sφ) (Ψ the Laplace CDF, β = 1/s), α = 1 − exp(−σδ)",
}
#: most samples per ray a volume renderer takes (64 times the 1,024 of the lecture's finest
#: sampling; the claims' paths end at 4,096): one ray's samples, points and φ temporaries
#: (~100 bytes a sample for a primitive, ~1 KB for a neural field) stay under 100 MB
MAX_SAMPLES = 2**16
#: most coarse samples of the importance sampler: its inverse CDF counts, for each of the
#: ≤ MAX_SAMPLES quantiles, the coarse bins below it (one ray: ≤ 2^26 counts, 0.5 GB as int64)
MAX_COARSE = 2**10
SAMPLERS = {
    "uniform": "bin midpoints of N equal bins of [t_min, t_max]",
    "stratified": "one uniform random point per bin (seeded)",
    "band": "N equal bins of the near-surface band [t̂ − Δ, t̂ + Δ] around the given hit t̂",
    "importance": "n_coarse uniform samples, then N more by inverse-CDF of their weights (NeRF hierarchical)",
}


def _specs() -> list[MethodSpec]:
    specs = [
        MethodSpec(
            name="sphere_trace",
            family="root",
            knobs=(
                Knob("tol", 1e-10, float, 0.0, "stop when |φ(o + t d)| ≤ tol", role="tolerance"),
                _MAX_STEPS,
                Knob("omega", 1.0, float, 1.0, "over-relaxation factor ω (Keinert et al. 2014; 1 = plain)", 1.99, role="setting"),
                _BOUNDS,
            ),
            requires=("lipschitz",), build=methods_root.build_sphere_trace,
            description="Hart's sphere tracing t ← t + ω|φ|/L from t_min until |φ| ≤ tol "
            "(lecture: 'Sphere Tracing'); L is the scene's Lipschitz bound; ω > 1 with the safe fallback",
        ),
        MethodSpec(
            name="hybrid_secant",
            family="root",
            knobs=(_CERT_XTOL, _MIN_STEP, _OVERSTEP, _HYBRID_MAX_STEPS, _BOUNDS, _LADDER, _LADDER_AFTER, _EXTRAPOLATE,
                   _REACH),
            requires=("lipschitz",), build=methods_root.build_hybrid,
            description="IDR-style hybrid: sphere tracing with steps max(|φ|/L, Δ) to the first sign change, Δ in "
            "[min_step, overstep] halved while a step is not certified by overlapping unbounding spheres (and at "
            "least the secant's extrapolation past a shallow approach, within reach), in ladder steps of several "
            "samples after ladder_after steps, then safeguarded secant on the bracket",
        ),
        MethodSpec(
            name="hybrid_chandrupatla",
            family="root",
            knobs=(_CERT_XTOL, _MIN_STEP, _OVERSTEP, _HYBRID_MAX_STEPS, _BOUNDS, _LADDER, _LADDER_AFTER, _EXTRAPOLATE,
                   _REACH),
            requires=("lipschitz",), build=methods_root.build_hybrid_chandrupatla, libs=_REFINE_LIBS["chandrupatla"],
            description="hybrid_secant's certified march to the first sign change, then "
            + _REFINE_DOC["chandrupatla"],
        ),
    ]
    for refine, doc in _REFINE_DOC.items():
        specs.append(MethodSpec(
            name=f"march_{refine}",
            family="root",
            knobs=(_CERT_XTOL, Knob("step", 1e-2, float, 1e-9, "marching step Δ (features thinner than Δ are missed)", role="step"),
                   Knob("max_steps", 4096, int, 1, "budget of marching plus refinement steps", role="budget"), _BOUNDS, _LADDER,
                   _LADDER_AFTER),
            requires=(), build=methods_root.march_builder(refine), libs=_REFINE_LIBS.get(refine),
            description=f"march with constant step Δ to the first sign change (DVR/UNISURF), then {doc}",
        ))
    # an engine's own ray query (impls/engine.py): no array-library backend runs it (libs=()), only
    # the engine plug-ins whose methods() name it; float32, the precision the engines compute in
    specs.append(MethodSpec(
        name="raycast",
        family="root",
        knobs=(),
        requires=(), libs=(), dtypes=("float32",),
        description="the engine's own first-hit ray query (BVH over the mesh's triangles, or the engine's SDF-grid "
        "intersector); no knobs; precision as the engine computes",
    ))
    specs += [
        MethodSpec(
            name="normal", family="gradient", knobs=(), requires=("smooth",), needs_t_hit=True,
            outputs=("normal",),
            description="unit normal n = ∇φ/|∇φ| at x = o + t_hit d (lecture 'Properties - Normal')",
        ),
        MethodSpec(
            name="curvature", family="gradient", knobs=(), requires=("smooth",), needs_t_hit=True,
            outputs=("curvature_laplacian", "curvature_divergence", "gaussian_curvature", "normal"),
            description="Δφ = tr H (lecture's 'mean curvature'), ∇·(∇φ/|∇φ|) = (tr H − nᵀHn)/|∇φ| "
            "(= κ1 + κ2 for any φ), Gaussian K = ∇φᵀ adj(H) ∇φ / |∇φ|⁴ (Goldman 2005)",
        ),
        MethodSpec(
            name="dt_implicit", family="param_grad", knobs=(_MIN_COS,), requires=("smooth",), needs_t_hit=True,
            outputs=("dt_dtheta",),
            description="implicit differentiation dt/dθ = −∂φ/∂θ / ⟨∇φ, d⟩ at the hit (lecture eq. 7–8)",
        ),
        MethodSpec(
            name="dt_idr", family="param_grad", knobs=(_MIN_COS,), requires=("smooth",), needs_t_hit=True,
            outputs=("dt_dtheta",),
            description="IDR's forward trick t(θ) = t̂ − φ(x̂; θ)/sg(⟨∇φ(x̂; θ0), d⟩) differentiated by autodiff "
            "(lecture, 'Forward implementation'); t is the corrected depth",
        ),
        MethodSpec(
            name="dt_unrolled", family="param_grad",
            knobs=(Knob("steps", 64, int, 1, "number of unrolled sphere-tracing steps", role="budget"), _MIN_COS),
            requires=("lipschitz", "smooth"), needs_t_hit=False, outputs=("dt_dtheta",),
            description="differentiable sphere tracing t_{k+1} = t_k + φ(x_k; θ)/L from t_min (lecture eq. 16), "
            "differentiated through every step; t is t_steps",
        ),
        MethodSpec(
            name="dt_finite_diff", family="param_grad",
            knobs=(Knob("h", 1e-6, float, 1e-14, "central-difference step on each θ_i (relative to max(1, |θ_i|); at least √ε of the dtype)", role="step"),
                   _MIN_COS),
            requires=("smooth",), needs_t_hit=True, outputs=("dt_dtheta",),
            description="central differences (t(θ + h e_i) − t(θ − h e_i))/2h, each t re-solved by Newton from t_hit",
        ),
        MethodSpec(
            name="render_surface", family="render",
            knobs=(_CERT_XTOL, _MIN_STEP, _OVERSTEP, _HYBRID_MAX_STEPS, _BOUNDS, _LADDER, _LADDER_AFTER, _EXTRAPOLATE,
                   _REACH),
            requires=("lipschitz",), outputs=("color",), needs_color=True, build=methods_root.build_hybrid,
            description="surface rendering: colour ρ(x̂) at the first hit found by hybrid_secant; 0 for a miss",
        ),
    ]
    for density, ddoc in DENSITIES.items():
        for sampler, sdoc in SAMPLERS.items():
            # the caps bound one ray's memory: a block holds at least one ray, whose samples (and,
            # importance, its (n_samples, n_coarse) bin count) must fit however few rays there are
            knobs = [Knob("n_samples", 64, int, 1, "samples per ray N", MAX_SAMPLES, role="budget"),
                     Knob("sharpness", 50.0, float, 1e-9, "density sharpness s (1/β)", role="setting"),
                     Knob("t_threshold", 0.0, float, 0.0, "early termination when transmittance < this (0: off)", 1.0, role="setting")]
            if sampler == "band":
                knobs.append(Knob("delta", 0.1, float, 1e-12, "half-width Δ of the band [t̂ − Δ, t̂ + Δ]", role="step"))
            if sampler == "stratified":
                knobs.append(Knob("seed", 0, int, 0, "seed of the stratified jitter", role="seed"))
            if sampler == "importance":
                knobs.append(Knob("n_coarse", 32, int, 1, "coarse uniform samples that build the importance pdf",
                                  MAX_COARSE, role="budget"))
            specs.append(MethodSpec(
                name=f"volume_{density}_{sampler}", family="render", knobs=tuple(knobs), requires=(),
                needs_t_hit=sampler == "band", outputs=("color", "opacity", "samples_used", "work_saved"), needs_color=True,
                finite_range=True,
                description=f"volume rendering by alpha compositing C = Σ T_i α_i ρ(x_i), T_i = Π_{{j<i}}(1 − α_j) "
                f"(lecture eq. 9–10); {ddoc}; samples: {sdoc}",
            ))
    return specs


METHODS: dict[str, MethodSpec] = {m.name: m for m in _specs()}


def get_method(name: str) -> MethodSpec:
    try:
        return METHODS[name]
    except KeyError:
        raise ValueError(f"unknown method {name!r}; known methods: {sorted(METHODS)}") from None
