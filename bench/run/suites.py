"""Suites: which cases, methods, dtypes and knob sweeps a run crosses with the backends.

A knob sweep is a list of knob dicts; each becomes one timed configuration (one point on the
backend's time-versus-error curve).  A method needs no entry here: its sweep is derived from
its knobs (:func:`default_sweep`), so a method added to ``impls.methods.METHODS`` is benchmarked
without touching ``bench/``.  ``Suite.sweeps`` overrides the derived sweep for a method.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np


@dataclasses.dataclass(frozen=True)
class Suite:
    """What a run crosses with the backends.

    name; case glob(s) and required tags; dtypes; ``sweeps`` (method → knob dicts) overriding
    the derived sweep; ``methods`` (None: every method in ``METHODS``); ``level`` passed to
    :func:`default_sweep` ("quick" or "full"); ``main_dial_only``: sweep only a method's first
    knob (its main accuracy dial, by the catalog's convention), the others at their defaults;
    ``sweep_cases``: a method's knob sweep runs on its first N applicable cases, the other
    applicable cases get its default knobs only (None: the sweep everywhere); ``max_cases``:
    a method runs on at most this many applicable cases (None: all); ``min_time_s`` and
    ``min_repeats``: timing per configuration; ``budget_s``: wall-clock guard of a run against a
    hang (None: none; the CLI's ``--budget`` overrides; a run that spends it is incomplete, says
    so and exits non-zero).  The built-in suites have none: a run's coverage never depends on
    the machine's speed or load;
    ``expensive_references``: check against references that cost seconds to minutes per case
    (the continuous rendering integral); when False those quantities are skipped rows saying so;
    ``small_cases_first``: a method's applicable cases are taken fewest rays first (so with
    ``max_cases`` a budgeted suite spends its time on methods, not on ray count);
    ``diverse_cases``: a method's applicable cases are taken one per scene family (the case id's
    first component: sphere, torus, csg, mlp, …) in turn, after those of ``lead_cases[family]``
    (else ``lead_cases["*"]``) that apply (the first is where the sweep runs), so ``max_cases`` cases cover as many kinds of scene as
    possible; ``secondary_dtype_cases``: dtypes after the first run default
    knobs on a method's first N cases only (None: everything in every dtype).
    """

    name: str
    case_pattern: str
    dtypes: tuple[str, ...]
    sweeps: dict[str, list[dict]]
    case_tags: tuple[str, ...] = ()
    methods: tuple[str, ...] | None = None
    level: str = "quick"
    min_time_s: float = 0.2  # timed seconds per configuration (CLI --min-time overrides)
    main_dial_only: bool = False
    sweep_cases: int | None = None
    max_cases: int | None = None
    min_repeats: int = 5
    budget_s: float | None = None
    expensive_references: bool = True
    small_cases_first: bool = False
    diverse_cases: bool = False
    lead_cases: dict = dataclasses.field(default_factory=lambda: {
        "*": ("sphere.camera.64x64",),
        "root": ("sphere.camera.64x64", "csg.union.camera.32x32", "mlp.camera.32x32"),
        # volume renderers share their cases, so each rendering integral (per case and density) is
        # computed once; smooth scenes, where the integral costs ~0.1 s per ray, not ~1 s (kinks)
        "render": ("sphere.camera.64x64", "torus.camera.32x32", "algsphere.camera.32x32")})
    secondary_dtype_cases: int | None = None
    #: with ``diverse_cases``: rotate the scene families by method, so that methods cover
    #: different families (False: every method of a family on the same cases, which "which to
    #: pick" compares)
    rotate_families: bool = True
    #: method family or name → case-id globs the suite does not plan for it (too costly for its
    #: purpose; both the family's and the method's own apply).  ``--case '*'`` keeps them out too
    #: (the catalog sweep would otherwise spend --timeout on each: 60 configurations, 2 h of the
    #: quick suite's); a ``--case`` that names cases any other way runs them
    exclude_cases: dict = dataclasses.field(default_factory=dict)
    #: method name or family → case-id globs it also runs on, at default knobs, wherever it
    #: applies, beyond ``max_cases`` (the workload scenes a suite must cover); a method's own
    #: name takes precedence over its family
    always_cases: dict = dataclasses.field(default_factory=dict)
    #: method name or family → globs of the cameras at scale (catalog tag ``large``: 256² and 1024²
    #: rays, which no suite selects by its pattern) it also runs on, at default knobs, in the
    #: suite's first dtype, wherever it applies
    scale_cases: dict = dataclasses.field(default_factory=dict)
    #: the suite run after this one as its stability stage (accuracy only, into ``stability/``
    #: under the run directory; :func:`bench.studies.stability.run_stage`), or None
    stability: str | None = None
    #: backend id or library → the dtypes a stage runs on it (default: the suite's dtypes); a pair
    #: left out is named in the report's stability section as not planned
    backend_dtypes: dict = dataclasses.field(default_factory=dict)
    #: backend id or library → the methods a stage runs on it (default: the suite's)
    backend_methods: dict = dataclasses.field(default_factory=dict)

    def sweep_for(self, spec) -> list[dict]:
        if spec.name in self.sweeps:
            return [dict(k) for k in self.sweeps[spec.name]]
        return default_sweep(spec, self.level, main_dial_only=self.main_dial_only)


def _is_tolerance(knob) -> bool:
    """A knob the suites sweep over decades: its declared role (``impls.methods.KNOB_ROLES``)."""
    return knob.role == "tolerance"


def _is_budget(knob) -> bool:
    """A knob the suites sweep geometrically up to its default: its declared role."""
    return knob.role == "budget"


def _int_values(knob, level: str) -> list[int]:
    """Geometric values of an integer budget (steps, iterations, samples) up to its default
    (quick) or 4× its default (full), at least ``max(low, 1)``; the default is always included."""
    lo = max(int(knob.low), 1)
    hi = max(int(knob.default), lo) * (1 if level == "quick" else 4)
    n = 3 if level == "quick" else 7
    # rounded to powers of two so sweeps read well and repeat across methods
    vals = {int(2 ** round(math.log2(v))) for v in np.geomspace(max(lo, 2) if hi > 2 else lo, hi, n)}
    vals |= {int(knob.default)}
    return sorted(v for v in vals if v >= lo)


def _tol_values(knob, level: str) -> list[float]:
    ks = (4, 8, 12) if level == "quick" else range(2, 14)  # quick: the report's error targets
    return [10.0 ** -k for k in ks if 10.0 ** -k >= knob.low]


def default_sweep(spec, level: str = "quick", main_dial_only: bool = False) -> list[dict]:
    """One-at-a-time sweep over a method's accuracy knobs, derived from its :class:`Knob` list.

    * a knob's own ``sweep`` (:class:`~impls.methods.Knob`, a tuple of values), if it has one: used as is;
    * a knob of role ``tolerance`` (its :class:`~impls.methods.Knob` declares it): 1e-4, 1e-8, 1e-12
      (quick: the report's error targets) or every decade 1e-2 … 1e-13 (full), the others at defaults;
    * a knob of role ``budget`` (steps, iterations, samples): 3 (quick) or 7 (full) geometric
      values, rounded to powers of two, up to its default (quick) or 4× it (full), with every
      tolerance at its tightest swept value so the budget is what limits the error (a
      convergence curve in the budget);
    * knobs of role ``step``, ``seed`` and ``setting`` stay at their defaults unless they name a
      ``sweep``.
    With ``main_dial_only`` only the first knob is swept.  The first knob dict is always the
    all-defaults setting.  Knob dicts are complete (every knob named) and unique, in a stable order.
    """
    knobs = list(spec.knobs)
    swept = knobs[:1] if main_dial_only else knobs
    base = {k.name: k.default for k in knobs}
    tight = {}
    for k in knobs:
        if k.sweep is None and _is_tolerance(k):
            vals = _tol_values(k, level)
            if vals:
                tight[k.name] = min(vals)
    out: list[dict] = [dict(base)]
    for k in swept:
        explicit = k.sweep
        if explicit is not None:
            out += [{**base, k.name: v} for v in explicit]
        elif _is_tolerance(k):
            out += [{**base, k.name: v} for v in _tol_values(k, level)]
        elif _is_budget(k):
            out += [{**base, **tight, k.name: v} for v in _int_values(k, level)]
    seen, unique = set(), []
    for kd in out:
        key = tuple(sorted((n, float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else str(v))
                           for n, v in kd.items()))
        if key not in seen:
            seen.add(key)
            unique.append(kd)
    return unique


def _root_methods() -> tuple[str, ...]:
    """The catalog's root finders (family ``root``), in catalog order."""
    from impls.methods import METHODS

    return tuple(name for name, spec in METHODS.items() if spec.family == "root")


#: the workload scenes (meshes, grid SDFs, the trained neural SDF) on every root finder, the surface
#: renderer and the gradients where they apply.  Not the volume renderers: their reference, the
#: rendering integral, costs 0.1–1 s per ray on these fields (``--case 'mesh.*'`` runs them).
_WORKLOAD_GLOBS = ("mesh.*", "grid.*", "neural.*")
_WORKLOADS = {"root": _WORKLOAD_GLOBS, "render_surface": _WORKLOAD_GLOBS, "gradient": _WORKLOAD_GLOBS,
              "param_grad": _WORKLOAD_GLOBS}
#: dt/dθ methods whose cost grows with the parameter count P: finite differences solve 2P rays'
#: roots again, unrolled differentiation carries P tangents through every step.  On the neural
#: SDF (P = 4481) each takes over 120 s on numpy and torch for 256 rays; ``--case 'neural.*'
#: --method dt_finite_diff`` runs them.  The implicit-function methods (one adjoint per ray) stay.
_PER_PARAMETER = {"dt_finite_diff": ("neural.*",), "dt_unrolled": ("neural.*",)}
#: the full suite's cameras at scale: the certified root finders and the surface renderer on the
#: analytic, CSG and grid scenes at 1024² and the torus mesh at 256²; the engines' raycast on the
#: mesh at both sizes.  Not the mesh at 1024² for the root finders (φ is a host call into libigl:
#: minutes per configuration, past --timeout) and not the neural SDF at scale (its certified
#: numerical reference takes minutes at 256² and hours at 1024²): ``--case`` names them.
_AT_SCALE = ("torus.camera.1024x1024", "csg.union.camera.1024x1024", "grid.torus64.camera.1024x1024",
             "mesh.torus.camera.256x256")
_SCALE = {"hybrid_secant": _AT_SCALE, "hybrid_chandrupatla": _AT_SCALE, "sphere_trace": _AT_SCALE,
          "render_surface": _AT_SCALE, "raycast": ("mesh.*.camera.256x256", "mesh.*.camera.1024x1024")}

SUITES = {
    # quick: CI and the README's first command, a showcase: every method on the same four scene
    # kinds where they apply (sphere grazing rays, torus, CSG torus ∪ box, the MLP; the next quick
    # cases where one does not), its main dial at 3 settings on the first (a short time-versus-error
    # curve per method and backend) and defaults on the others, float64, 0.02 s and ≥ 3 samples of
    # timing each (0.05 s cost 26 CPU-s more of a warm run's 180 and left the samples' spread the same:
    # interquartile range / median 3–8 % at the median configuration either way, docs/performance.md);
    # volume renderers against ρ(x*) only (the rendering integral costs ~10 s to
    # minutes per case); then the stability stage (below).  The workload scenes tagged "quick" (the
    # torus mesh, the neural SDF) run on every root finder, the surface renderer and the gradients
    # (not dt/dθ: the neural SDF's 4481 weights cost 2–120 s a configuration).
    "quick": Suite(name="quick", case_pattern="*", case_tags=("quick",), dtypes=("float64",), sweeps={}, level="quick",
                   min_time_s=0.02, main_dial_only=True, max_cases=4, sweep_cases=1, min_repeats=3, budget_s=None,
                   expensive_references=False, small_cases_first=True, diverse_cases=True, rotate_families=False,
                   lead_cases={"*": ("sphere.grazing.1e-6", "torus.camera.32x32", "csg.union.camera.32x32",
                                     "mlp.camera.32x32"),
                               # dt_finite_diff on the MLP's 350 weights: 13 s a call on torch (700 × 8 torch.func.jvp calls)
                               "param_grad": ("sphere.grazing.1e-6", "torus.camera.32x32", "csg.union.camera.32x32",
                                              "box.camera.32x32")},
                   exclude_cases={"param_grad": ("mlp.camera.32x32", "neural.*")}, stability="stability.quick",
                   always_cases=_WORKLOADS),
    # full: < 15 min on 2 cores.  Each method on 3 applicable cases from different scene
    # families, float64; its main dial swept over the full range (every decade of a tolerance,
    # 7 budgets) on the first, with the continuous rendering integral as the volume renderers'
    # reference; float32 at default knobs on the first case (the precision floor).  0.05 s and
    # ≥ 3 samples of timing each.  Defaults everywhere are measured before any sweep point.  No
    # time budget: every run covers its whole plan (a --budget is a guard against a hang).  Every case of the catalog is
    # still run by some method; ``--case '*'`` runs a method on all of its cases.  The workload
    # scenes (meshes, grid SDFs, the neural SDF) run on every applicable method at default knobs.
    # stability: every root finder at default knobs, float64 and float32, on the one representative
    # case per adversarial ray family (catalog tag "stability"), accuracy only (one call per
    # configuration): the report's stability matrix.  The quick suite runs it as a stage of its
    # own (``Suite.stability``) into the run directory's ``stability/``, apart from the rows the
    # committed baseline gates.
    "stability": Suite(name="stability", case_pattern="*", case_tags=("stability",), dtypes=("float64", "float32"),
                       sweeps={}, level="quick", main_dial_only=True, sweep_cases=0, expensive_references=False,
                       methods=_root_methods(), min_time_s=0.0, min_repeats=1),
    # the quick suite's stage: the same plan, but jax in float64 only and on its two Lipschitz
    # tracers — jax compiles once per (method, scene, dtype, shape), ~1.5–3 s each on 2 cores, so
    # its whole plan alone would add ~4 minutes; numpy and torch (no compilation) run it all in
    # seconds.  `--suite stability` runs everything everywhere.
    "stability.quick": Suite(name="stability.quick", case_pattern="*", case_tags=("stability",),
                             dtypes=("float64", "float32"), sweeps={}, level="quick", main_dial_only=True,
                             sweep_cases=0, expensive_references=False, methods=_root_methods(), min_time_s=0.0,
                             min_repeats=1, backend_dtypes={"jax": ("float64",)},
                             backend_methods={"jax": ("sphere_trace", "hybrid_secant")}),
    "full": Suite(name="full", case_pattern="*", dtypes=("float64", "float32"), sweeps={}, level="full",
                  min_time_s=0.05, min_repeats=3, main_dial_only=True, sweep_cases=1, max_cases=3,
                  diverse_cases=True, secondary_dtype_cases=1, budget_s=None,
                  always_cases=_WORKLOADS, exclude_cases=_PER_PARAMETER, scale_cases=_SCALE),
    # workloads: the mesh, grid-SDF and neural-SDF cases only, every root finder, the surface
    # renderer, the gradients and the implicit dt/dθ at default knobs, float64, timed like full:
    # "which to pick" on the fields people trace (the full suite runs the same configurations
    # among its others)
    "workloads": Suite(name="workloads", case_pattern=",".join(_WORKLOAD_GLOBS), dtypes=("float64",), sweeps={},
                       level="full", min_time_s=0.05, min_repeats=3, main_dial_only=True, sweep_cases=0,
                       expensive_references=False,
                       methods=(*_root_methods(), "render_surface", "normal", "curvature", "dt_implicit", "dt_idr")),
}


def get_suite(name: str) -> Suite:
    try:
        return SUITES[name]
    except KeyError:
        raise ValueError(f"unknown suite {name!r}; choose one of {sorted(SUITES)} (--suite)") from None

