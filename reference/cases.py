"""The case catalog: scenes × seeded ray families with stable dotted ids.

One catalog, imported by tests (``pytest`` ids) and by ``bench`` (report rows, baseline keys),
in the spirit of scipy's ``optimize/_tstutils.py``.  A case id is stable across versions
(``sphere.camera.64x64``); the case *version* is a content hash of everything that determines
its answers (scene spec, rays, search interval), so a baseline row is only compared with a row
of the same version.
"""

from __future__ import annotations

import dataclasses
import fnmatch
import functools
import hashlib
import json
from typing import Any, Callable

import numpy as np

from . import rays as _rays
from .primitives import Sphere
from .scene import Field, FieldError, field_label, user_defined


class NoExactAnswer(ValueError):
    """The reference has no exact answer for this quantity on this case: its scene states none
    (a :class:`reference.scene.SceneInfo` flag is False) or a node does not implement it.  The
    message names the case and why.  A ValueError, as the answers raised before this type."""


@dataclasses.dataclass(frozen=True, eq=False)
class Case:
    """A scene plus a ray family and the search interval [t_min, t_max] along each ray.

    ``origins`` and ``directions`` are float64 ``(n, 3)``; directions are unit vectors.
    """

    id: str
    scene: Field
    origins: np.ndarray
    directions: np.ndarray
    t_min: float = 0.0
    t_max: float = 10.0
    tags: tuple[str, ...] = ()
    description: str = ""
    color_frequency: float = 2.0

    def __post_init__(self):
        # the rays are the truth every row is measured against: read-only views, so that code
        # writing into them (a backend's in-place "fix-up" of its inputs) raises instead of
        # changing the case for every other row (the builder's own arrays stay writable)
        for name in ("origins", "directions"):
            view = np.asarray(getattr(self, name)).view()
            view.flags.writeable = False
            object.__setattr__(self, name, view)
        freeze_arrays(self.scene, set())

    @property
    def n_rays(self) -> int:
        return int(self.origins.shape[0])

    @functools.cached_property
    def version(self) -> str:
        h = hashlib.sha256()
        h.update(json.dumps(self.scene.spec(), sort_keys=True).encode())
        h.update(np.ascontiguousarray(self.origins, np.float64).tobytes())
        h.update(np.ascontiguousarray(self.directions, np.float64).tobytes())
        h.update(repr((self.t_min, self.t_max)).encode())
        return h.hexdigest()[:12]

    # -- exact answers ---------------------------------------------------------------------
    #
    # Every exact answer of the case is computed once and kept in one cache on the case
    # (:meth:`_answer`), a missing answer (:class:`NoExactAnswer`) included; tests and bench's
    # metrics read them from here.

    def _answer(self, key, compute):
        """``compute()`` memoised under ``key`` in the case's cache of exact answers.  A
        :class:`NoExactAnswer` is remembered and raised again (not recomputed); other errors
        (e.g. a scene without a Lipschitz bound for the numerical reference) are not cached."""
        cache = self.__dict__.setdefault("_exact_cache", {})  # frozen dataclass: set in __dict__ directly
        if key not in cache:
            try:
                cache[key] = compute()
            except NoExactAnswer as exc:
                cache[key] = exc
        val = cache[key]
        if isinstance(val, NoExactAnswer):
            raise val.with_traceback(None)
        return val

    def preload_answer(self, key: str, compute: Callable[[], Any]) -> None:
        """Memoise ``compute()`` as the answer ``key`` (as :meth:`_answer` would compute it), unless
        the case has it already: how a caller that keeps answers elsewhere (bench's cache directory)
        hands one back.  ``"t"``: ``(exact_t, per-ray error bounds or None)``."""
        self._answer(key, compute)

    @property
    def exact_t(self) -> np.ndarray:
        """First-hit depth per ray in (t_min, t_max]; ``inf`` for a miss, NaN where the reference
        has no answer (a Lipschitz bound seen to be false).  Closed form where the scene has exact
        hits, else the numerical reference (:mod:`reference.numerical`); each ray's depth bound
        is :attr:`exact_t_error_bounds`."""
        return self._exact_t_and_bound[0]

    @property
    def exact_t_error_bounds(self) -> np.ndarray:
        """Per ray, a bound on |exact_t − t*|, t* the first root of the real-number φ along the
        real-number ray (:mod:`reference.depthbound`): the float64 φ's rounding over the slope
        |dφ/dt|, widened to second order on grazing rays; 0 at a miss.  NaN where float64 cannot
        certify a crossing there (a near-tangent ray, or a possible tangency the numerical scan
        could not resolve) and inf where the reference has no answer: those rays are *flagged*
        (:attr:`judged_mask` is False), and a method's answer there is not judged."""
        return self._answer("t_bounds", self._depth_bounds)

    @property
    def judged_mask(self) -> np.ndarray:
        """Rays whose reference answer is certified (a finite :attr:`exact_t_error_bounds`, a
        depth that is not NaN): the rays a method's depth, hit or miss is judged on."""
        return self._answer("judged", lambda: np.isfinite(self.exact_t_error_bounds) & ~np.isnan(self.exact_t))

    @property
    def exact_t_error_bound(self) -> float:
        """The largest :attr:`exact_t_error_bounds` over the judged rays (0 when none is)."""
        b = self.exact_t_error_bounds
        return float(np.max(b[self.judged_mask], initial=0.0))

    def _truth_scene(self) -> Field:
        # a planted lie about L (DeclaredLipschitz) is not what certifies the truth: its child's
        # own bound does (the lie itself is flagged by the reference: see the understated cases)
        return self.scene.child if isinstance(self.scene, DeclaredLipschitz) else self.scene

    @property
    def _exact_t_and_bound(self) -> tuple[np.ndarray, np.ndarray | None]:
        def compute():
            if self.scene.info.exact_hits:
                t = self._checked_first_hit()
                return np.where(t <= self.t_max, t, np.inf), None  # bounds: _depth_bounds, on demand
            return self.numerical_hits()

        return self._answer("t", compute)

    def _checked_first_hit(self) -> np.ndarray:
        """The scene's closed-form first hits, checked (a :class:`FieldError` naming the field):
        one real depth per ray, inf for a miss, never NaN (a NaN became a judged MISS, charging
        every backend's hit there as false); and where the scene holds a user's node (its
        ``first_hit`` is then the user's claim, not the library's tested formula) and has a
        Lipschitz bound, the same as the numerical reference's first crossing (:meth:`numerical_hits`)
        within that reference's error bound (+ 64 float64 spacings) on every ray it judges: a
        ``first_hit`` that returned the exit, or inf on every other hit, charged a correct
        backend 2.0 of depth error or 1,512 false hits (the 2026-12-01 user-field probe)."""
        scene, n = self.scene, self.n_rays
        label = field_label(scene)
        try:
            t = np.asarray(scene.first_hit(self.origins, self.directions, self.t_min), dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise FieldError(f"{label}: first_hit did not return real depths ({type(exc).__name__}: {exc}); it returns "
                             "one depth per ray, inf for a miss") from exc
        if t.shape != (n,):
            raise FieldError(f"{label}: first_hit returned shape {t.shape}, expected ({n},): one depth per ray, inf for "
                             "a miss")
        if np.isnan(t).any():
            i = int(np.flatnonzero(np.isnan(t))[0])
            raise FieldError(f"{label}: first_hit returned NaN on {int(np.isnan(t).sum())} of {n} rays (ray {i}); it "
                             "returns a depth, or inf for a miss (without closed-form hits, leave exact_hits False and "
                             "the numerical reference answers)")
        nodes = list(scene.walk()) if hasattr(scene, "walk") else [scene]
        if any(user_defined(x) for x in nodes) and scene.info.lipschitz:
            tn, err = self.numerical_hits()
            tc = np.where(t <= self.t_max, t, np.inf)
            with np.errstate(invalid="ignore"):
                same = (np.isinf(tc) & np.isinf(tn)) | (
                    np.abs(tc - tn) <= err + 64 * np.finfo(np.float64).eps * np.maximum(1.0, np.abs(tn)))
            off = np.isfinite(err) & ~same
            if off.any():
                i = int(np.flatnonzero(off)[0])
                raise FieldError(f"{label}: first_hit disagrees with the numerical reference's first crossing on "
                                 f"{int(off.sum())} of {n} rays (ray {i}: first_hit {float(tc[i])!r}, numerical {float(tn[i])!r} ± "
                                 f"{err[i]:.3g}); fix first_hit (the first crossing of φ in [t_min, t_max], inf for a "
                                 "miss), or leave exact_hits False and the numerical reference answers")
        return t

    def numerical_hits(self) -> tuple[np.ndarray, np.ndarray]:
        """(first-hit depths, per-ray error bounds) by the numerical reference
        (:func:`reference.numerical.first_hit_numeric`), not memoised: what :attr:`exact_t` is
        for a scene without closed-form hits."""
        from .numerical import first_hit_numeric

        return first_hit_numeric(self._truth_scene(), self.origins, self.directions, self.t_min, self.t_max)

    def _depth_bounds(self) -> np.ndarray:
        t, err = self._exact_t_and_bound
        if err is not None:
            return np.asarray(err, np.float64)
        from .depthbound import depth_bounds

        return depth_bounds(self._truth_scene(), self.origins, self.directions, t)

    @property
    def hit_mask(self) -> np.ndarray:
        """Rays with a first hit in (t_min, t_max] (finite :attr:`exact_t`), (n,) bool."""
        return self._answer("hit_mask", lambda: np.isfinite(self.exact_t))

    @property
    def exact_points(self) -> np.ndarray:
        """x* = o + t* d at hits, NaN rows elsewhere, (n, 3)."""

        def compute():
            x = np.full(self.origins.shape, np.nan)
            m = self.hit_mask
            x[m] = self.origins[m] + self.exact_t[m, None] * self.directions[m]
            return x

        return self._answer("points", compute)

    def _at_hits(self, what: str, flag: str, fn, tails: tuple[tuple[int, ...], ...]) -> tuple[np.ndarray, ...]:
        """``fn(x*)`` at the exact hit points, each of its arrays (``fn`` returns one, or a tuple)
        scattered to one row per ray with NaN rows at misses; ``tails`` are their shapes per point
        (what an all-miss case returns, without calling ``fn``).  The scene must state
        ``info.<flag>``; a node that still has no such answer (NotImplementedError) is a
        :class:`NoExactAnswer` too."""
        if not getattr(self.scene.info, flag):
            raise NoExactAnswer(f"no exact {what} for {self.id}: scene {type(self.scene).__name__} states "
                                f"{flag}=False (case.scene.info)")
        m = self.hit_mask
        if not m.any():
            return tuple(np.full((self.n_rays,) + tail, np.nan) for tail in tails)
        try:
            vals = fn(self.exact_points[m])
        except NotImplementedError as exc:
            raise NoExactAnswer(f"no exact {what} for {self.id}: {exc}") from None
        out = []
        for v in vals if isinstance(vals, tuple) else (vals,):
            v = np.asarray(v, np.float64)
            full = np.full((self.n_rays,) + v.shape[1:], np.nan)
            full[m] = v
            out.append(full)
        return tuple(out)

    @property
    def exact_normals(self) -> np.ndarray:
        """Outward unit normals n = ∇φ/|∇φ| at the hits (n, 3), NaN at misses
        (:meth:`reference.scene.Field.normal_exact`)."""
        return self._answer("normals",
                            lambda: self._at_hits("normals", "exact_normals", self.scene.normal_exact, ((3,),))[0])

    @property
    def exact_curvatures(self) -> tuple[np.ndarray, np.ndarray]:
        """(κ1, κ2) at the hits (κ1 ≥ κ2, convention of :mod:`reference.curvature`), NaN at
        misses and where the surface has an edge (:meth:`reference.scene.Field.curvatures_exact`)."""
        return self._answer("curvatures", lambda: self._at_hits("curvatures", "exact_curvature",
                                                                self.scene.curvatures_exact, ((), ())))

    @property
    def exact_dt_dtheta(self) -> np.ndarray:
        """dt/dθ at the hits (n, P) in ``scene.param_vector()`` order, NaN rows at misses:
        implicit differentiation of φ(o + t(θ) d; θ) = 0 (:meth:`reference.scene.Field.hit_param_grad`)."""

        def compute():
            if not self.scene.info.exact_hit_param_grad:
                raise NoExactAnswer(f"no exact dt/dθ for {self.id}: scene {type(self.scene).__name__} has no "
                                    "closed-form dt/dθ (exact_hit_param_grad=False)")
            try:
                return self.scene.hit_param_grad(self.origins, self.directions, self.exact_t)
            except NotImplementedError as exc:
                raise NoExactAnswer(f"no exact dt/dθ for {self.id}: {exc}") from None

        return self._answer("dt_dtheta", compute)

    @property
    def exact_surface_colors(self) -> np.ndarray:
        """ρ(x*), the case's colour field at the exact first hit (n, 3), NaN rows at misses: the
        limit a volume renderer approaches as its density sharpens."""

        def compute():
            field = self.color_field
            m = self.hit_mask
            out = np.full((self.n_rays, 3), np.nan)
            if m.any():
                x = self.exact_points[m]
                c = np.asarray(field.value(x) if hasattr(field, "value") else field(x), np.float64)
                out[m] = c.reshape(int(m.sum()), -1)
            return out

        return self._answer("surface_colors", compute)

    def exact_colors(self, model: str, sharpness: float):
        """The continuous volume-rendering reference of this case's rays with its colour field:
        ``(colors (n, 3), error_bound (n,), T(t_max) (n,))`` from
        :func:`reference.rendering.render_exact` on [max(t_min, 0), t_max]; cached per
        (model, sharpness).  Seconds per few tens of rays: ask for it on small cases."""

        def compute():
            from .rendering import render_exact

            return render_exact(self.scene, self.color_field, model, sharpness, self.origins, self.directions,
                                max(self.t_min, 0.0), self.t_max, return_transmittance=True)

        return self._answer(("colors", model, float(sharpness)), compute)

    @functools.cached_property
    def color_field(self):
        """The case's colour field ρ(x) (:class:`reference.rendering.SineColor`), with its
        Lipschitz constant; scaled to the scene's size."""
        from .rendering import SineColor

        return SineColor(frequency=self.color_frequency)


def freeze_arrays(value, seen: set) -> None:
    """Make every numpy array a scene holds read-only (its nodes' attributes, and the dicts,
    lists and tuples among them, its children included): the scene is the truth every row is
    measured against, and a backend that wrote into it (its weights, a mesh's vertices, a grid's
    values) would change it for every row after its own.  A write now raises in that backend."""
    if id(value) in seen:
        return
    seen.add(id(value))
    if isinstance(value, np.ndarray):
        value.flags.writeable = False
    elif isinstance(value, dict):
        for v in value.values():
            freeze_arrays(v, seen)
    elif isinstance(value, (list, tuple)):
        for v in value:
            freeze_arrays(v, seen)
    elif isinstance(value, Field):
        for v in getattr(value, "__dict__", {}).values():  # (a user's node may have __slots__ only)
            freeze_arrays(v, seen)
        for child in getattr(value, "children", ()) or ():
            freeze_arrays(child, seen)


_FACTORIES: dict[str, Callable[[], Case]] = {}
#: tags declared at registration (:func:`register_cases`), read by :func:`catalog` without building
_DECLARED_TAGS: dict[str, frozenset[str]] = {}


def make_case(case_id: str, scene: Field, origins, directions, *, tags: tuple[str, ...] = (), description: str = "",
              t_min: float = 0.0, t_max: float = 10.0, color_frequency: float = 2.0) -> Case:
    """The one case builder every case module uses: rays as contiguous float64 ``(n, 3)`` arrays,
    tags = the scene's structural tags (its kinds, ``sdf``, ``lipschitz``, ``csg``, …) then
    ``tags``, without repeats."""
    return Case(id=case_id, scene=scene, origins=np.ascontiguousarray(origins, np.float64),
                directions=np.ascontiguousarray(directions, np.float64), t_min=t_min, t_max=t_max,
                tags=case_tags(scene, tags), description=description, color_frequency=color_frequency)


def case_tags(scene: Field, tags: tuple[str, ...] = ()) -> tuple[str, ...]:
    """The tags :func:`make_case` gives a case of ``scene``: the scene's structural tags, then
    ``tags``, without repeats (what a builder declares to :func:`register_cases`)."""
    return tuple(dict.fromkeys(_scene_tags(scene) + tuple(tags)))


def register_cases(ids, build: Callable[[], list[Case]], tags: dict[str, tuple[str, ...]] | None = None) -> None:
    """The one way cases enter the catalog: ``ids`` are registered at once, without building
    anything; ``build()`` returns the cases (exactly ``ids``) and runs at most once, when the first
    of them is asked for (a stored mesh or network is loaded once for all of its cases).

    ``tags`` (optional) declares the tags of some or all of ``ids`` (id → tags, the scene's
    structural tags included): :func:`catalog` then selects those cases by tag without building
    them (a suite chosen by tag builds only what it runs).  A built case must carry exactly its
    declared tags, in any order; an AssertionError names the case and its builder otherwise."""
    ids = tuple(ids)
    declared = {cid: frozenset(t) for cid, t in (tags or {}).items()}
    if set(declared) - set(ids):
        raise ValueError(f"tags declared for ids not registered here: {sorted(set(declared) - set(ids))}")

    @functools.cache
    def built() -> dict[str, Case]:
        cases = {c.id: c for c in build()}
        name = getattr(build, "__qualname__", build)
        if set(cases) != set(ids):
            raise AssertionError(f"case builder {name!r} built {sorted(cases)}, registered as {sorted(ids)}")
        for cid, want in declared.items():
            if set(cases[cid].tags) != want:
                raise AssertionError(f"case builder {name!r} built {cid!r} with tags {sorted(cases[cid].tags)}, "
                                     f"declared as {sorted(want)}")
        return cases

    for cid in ids:
        if cid in _FACTORIES:
            raise ValueError(f"duplicate case id {cid!r}")
    for cid in ids:
        _FACTORIES[cid] = lambda cid=cid: built()[cid]
    _DECLARED_TAGS.update(declared)


def register_each(declared: dict[str, tuple[str, ...]], build: Callable[[str], Case]) -> None:
    """Register each id of ``declared`` (id → the case's tags) on its own: ``build(id)`` makes that
    case when it is first asked for, so a run builds only the cases it selects (the case modules
    that share a costly resource, a stored mesh or network, cache it themselves).  The tags are
    declared as in :func:`register_cases`."""
    for cid, tags in declared.items():
        register_cases((cid,), lambda cid=cid: [build(cid)], {cid: tags})


def register(case_id: str):
    """Decorator form of :func:`register_cases` for one zero-argument case factory."""

    def deco(fn: Callable[[], Case]):
        register_cases((case_id,), lambda: [fn()])
        return fn

    return deco


@functools.cache
def get_case(case_id: str) -> Case:
    try:
        factory = _FACTORIES[case_id]
    except KeyError:
        raise KeyError(f"unknown case {case_id!r}; `python -m bench cases` lists them") from None
    case = factory()
    if case.id != case_id:
        raise AssertionError(f"factory for {case_id!r} built a case with id {case.id!r}")
    return case


def case_ids() -> list[str]:
    return sorted(_FACTORIES)


def tags_of(case_id: str) -> tuple[str, ...]:
    """A case's tags: those declared at registration (:func:`register_cases`), sorted, without
    building the case (a mesh case's build loads its mesh), else the built case's in their order.
    KeyError for an unknown id, as :func:`get_case`."""
    if case_id not in _FACTORIES:
        get_case(case_id)  # (raises its KeyError)
    known = _DECLARED_TAGS.get(case_id)
    return tuple(sorted(known)) if known is not None else get_case(case_id).tags


#: the cameras at scale (256² and 1024² rays) carry this tag; the 1024² ones also :data:`FULL_ONLY`
LARGE = "large"
#: the tag of the cases meant for the ``full`` suite only (1024² cameras)
FULL_ONLY = "full"
#: the image sizes of the cameras at scale, and their ids' suffixes
LARGE_SIZES = (256, 1024)


def large_tags(n: int) -> tuple[str, ...]:
    """Tags of an n×n camera at scale: :data:`LARGE`, and :data:`FULL_ONLY` for 1024²."""
    return ("camera", LARGE) + ((FULL_ONLY,) if n >= 1024 else ())


def catalog(pattern: str | None = None, tags: set[str] | None = None) -> list[Case]:
    """All cases whose id matches the glob ``pattern`` and that carry every tag in ``tags``.

    Cases tagged :data:`LARGE` (cameras of 256² and 1024² rays: their references and a method's
    run take seconds to minutes each, on the host-call scenes far more) are listed only when asked
    for: ``tags`` containing ``large`` (or ``full``), or a pattern naming the id without a wildcard.
    :func:`case_ids` and :func:`get_case` know every case.  A case whose tags were declared at
    registration (:func:`register_cases`) is built only if it is selected."""
    out = []
    want_large = bool(tags) and bool({LARGE, FULL_ONLY} & set(tags))
    pats = pattern.split(",") if pattern else []
    for cid in case_ids():
        if pattern and not any(fnmatch.fnmatchcase(cid, p) for p in pats):
            continue
        known = _DECLARED_TAGS.get(cid)  # declared: no need to build the case to read them
        if known is None:
            known = get_case(cid).tags
        if tags and not set(tags) <= set(known):
            continue
        if LARGE in known and not (want_large or cid in pats):
            continue
        out.append(get_case(cid))
    return out


# -- the cases -------------------------------------------------------------------------------
#
# Tags say what a case exercises and needs: the scene's own kind, ``sdf`` (exact SDF),
# ``lipschitz`` (a Lipschitz bound exists), ``csg``, ``transform``, ``grazing``, ``tangent``,
# ``inside``, ``surface``, ``far``, ``scale``, ``thin``, ``parallel``, ``understated``,
# ``wall`` (through a mesh's thin wall), ``edge`` (grazing a mesh's edges), ``mesh``, ``grid``,
# ``camera``, ``mlp``, ``neural``, ``numerical`` (no closed-form hits), ``quick`` (the CI suite),
# ``large`` (cameras of 256² and 1024² rays, listed by :func:`catalog` only when asked for), ``full``
# (the 1024² ones, meant for the full suite only) and
# ``stability`` (the one representative case per adversarial family that the stability plan
# runs).  Tags are not part of a case's version.

#: the adversarial ray families (the stability matrix's columns), most specific first: a case
#: belongs to the first of these among its tags (``box.parallel`` is also ``grazing``, but its
#: family is ``parallel``)
ADVERSARIAL_FAMILIES = ("understated", "tangent", "parallel", "wall", "thin", "scale", "far", "surface", "inside", "edge",
                        "grazing")


def adversarial_family(tags) -> str | None:
    """The adversarial family of a case with ``tags`` (see :data:`ADVERSARIAL_FAMILIES`), or None."""
    tags = set(tags)
    return next((f for f in ADVERSARIAL_FAMILIES if f in tags), None)


@dataclasses.dataclass(frozen=True, eq=False)
class DeclaredLipschitz(Field):
    """A child field φ whose :class:`SceneInfo` declares ``lipschitz`` = ``declared`` instead of
    the child's own (true) bound: the same values, the same surface and the same closed-form
    answers (delegated to the child), only the claim about its slope differs.  With ``declared``
    below the true L it is a *lie* that a method trusting L (step φ/L) tunnels through, and the
    truth does not depend on L: hits come from the child's closed form, or, for a child without
    one, from the numerical reference certified by the child's own bound (:attr:`Case.exact_t`),
    not from one that would trust the declared bound."""

    child: Field = None
    declared: float = 1.0
    kind = "understated"
    declares_lipschitz = True

    def __post_init__(self):
        if not isinstance(self.child, Field):
            raise ValueError(f"child must be a Field (a scene node), got {type(self.child).__name__}")
        if not (np.isfinite(self.declared) and self.declared > 0):
            raise ValueError(f"declared must be a finite Lipschitz constant > 0, got {self.declared!r}")

    @property
    def children(self):
        return (self.child,)

    @property
    def info(self):
        ci = self.child.info
        return dataclasses.replace(ci, lipschitz=float(self.declared), exact_sdf=False, distance_bound=False)

    def bounding_sphere(self):
        return self.child.bounding_sphere()

    def domain_hulls(self):
        return self.child.domain_hulls()  # the same surface, and the declaration is for the child's domain

    def ray_bounds(self, xp, o, d):
        return self.child.ray_bounds(xp, o, d)

    def _eval(self, x, xp, cursor):
        return self.child._eval(x, xp, cursor)

    def ray_intervals(self, o, d):
        return self.child.ray_intervals(o, d)

    def ray_interval_batch(self, o, d):
        return self.child.ray_interval_batch(o, d)

    def first_hit(self, o, d, t_min: float = 0.0):
        return self.child.first_hit(o, d, t_min)

    def _jet(self, x):
        return self.child._jet(x)

    def curvatures_exact(self, x):
        return self.child.curvatures_exact(x)


def _scene_tags(scene: Field) -> tuple[str, ...]:
    info = scene.info
    structural = {"transform", "union", "intersection", "difference", "complement", "scaled"}
    tags = [scene.kind] + sorted({n.kind for n in scene.walk()} - structural - {scene.kind})
    if info.exact_sdf:
        tags.append("sdf")
    if info.lipschitz is not None:
        tags.append("lipschitz")
    if not info.exact_hits:
        tags.append("numerical")
    kinds = {n.kind for n in scene.walk()}
    if kinds & {"union", "intersection", "difference", "complement"}:
        tags.append("csg")
    if "transform" in kinds:
        tags.append("transform")
    return tuple(tags)


def _add(case_id: str, build: Callable[[], tuple], tags: tuple[str, ...] = (), description: str = "",
         t_min: float = 0.0, t_max: float = 10.0, color_frequency: float = 2.0, scene: Field | None = None) -> None:
    """Register ``case_id`` built lazily from ``build() -> (scene, origins, directions)``.  With
    ``scene`` (a cheap copy of the scene ``build`` makes) its tags are declared, so that the
    catalog skips the case without building its rays (the cameras at scale)."""
    register_cases((case_id,), lambda: [make_case(case_id, *build(), tags=tags, description=description, t_min=t_min,
                                                  t_max=t_max, color_frequency=color_frequency)],
                   None if scene is None else {case_id: case_tags(scene, tags)})


def _cam(n: int, eye=(0.0, 0.0, 3.0), look_at=(0.0, 0.0, 0.0), fov: float = 40.0, up=(0.0, 1.0, 0.0)):
    return _rays.pinhole(eye=eye, look_at=look_at, up=up, fov_deg=fov, width=n, height=n)


_add("sphere.camera.64x64", lambda: (Sphere(), *_cam(64)), ("quick", "camera"),
     "unit sphere seen by a 64×64 pinhole camera at distance 3 (fov 40°); the corners miss")


def _register_all() -> None:
    from .csg import Complement, Difference, Intersection, Union
    from .implicits import AlgebraicSphere, Ellipsoid, Scaled
    from .primitives import Box, CappedCylinder, Capsule, Plane, Torus
    from .transform import Transform

    # sphere ---------------------------------------------------------------------------------
    for k in (3, 6, 9, 12):
        _add(f"sphere.grazing.1e-{k}", lambda k=k: (Sphere(), *_rays.grazing_pm(256, k, 3.0, seed=k)),
             ("grazing",) + (("quick", "stability") if k == 6 else ()),
             f"unit sphere, impact parameters 1 ± 1e-{k} from distance 3 (half near misses)")
    for e in (3, 6):
        _add(f"sphere.far.1e{e}", lambda e=e: (Sphere(), *_rays.far(256, 10.0**e, 1.2, seed=e)),
             ("far",) + (("stability",) if e == 6 else ()),
             f"unit sphere seen from distance 1e{e} (rays aimed at the ball of radius 1.2)", t_max=2 * 10.0**e)
    _add("sphere.inside", lambda: (Sphere(), *_rays.in_ball(256, 0.999, seed=11)), ("inside", "stability"),
         "origins inside the unit sphere: the first hit is the exit")

    def _surface():
        rng = np.random.default_rng(12)
        o = _rays.normalize(rng.normal(size=(256, 3)))
        d = _rays.normalize(-o + 0.9 * _rays.normalize(rng.normal(size=(256, 3))))
        return Sphere(), o, d

    _add("sphere.surface", _surface, ("surface", "stability"),
         "origins on the unit sphere (to rounding), directions into it; t_min = −1e-9 so the "
         "answer is the hit at the origin itself (t ≈ 0)", t_min=-1e-9)
    for e, sgn in ((6, "-"), (6, "")):
        scale = 10.0 ** (-e if sgn else e)
        _add(f"sphere.scale.1e{sgn}{e}",
             lambda scale=scale: (Sphere(radius=scale), *_cam(32, eye=(0.0, 0.0, 3 * scale))),
             ("scale", "camera") + (("stability",) if sgn else ()), f"sphere of radius {scale:g} seen by a 32×32 camera at 3× its radius",
             t_max=10 * scale, color_frequency=2.0 / scale)

    # plane ----------------------------------------------------------------------------------
    _add("plane.camera.32x32", lambda: (Plane(), *_cam(32, eye=(0.0, -3.0, 1.0), fov=60.0, up=(0.0, 0.0, 1.0))),
         ("camera",), "ground plane z < 0 seen from height 1, the upper rows miss (horizon)", t_max=50.0)

    def _plane_grazing():
        rng = np.random.default_rng(13)
        a = 1e-6 * rng.uniform(0.5, 2.0, 256)
        o = np.stack([rng.uniform(-1, 1, 256), rng.uniform(-1, 1, 256), np.full(256, 1e-6)], axis=1)
        d = np.stack([np.cos(a), np.zeros(256), -np.sin(a)], axis=1)
        return Plane(), o, d

    _add("plane.grazing.1e-6", _plane_grazing, ("grazing",),
         "rays at angles ~1e-6 to the plane from height 1e-6 (hit near t ≈ 1)")

    # box ------------------------------------------------------------------------------------
    box = lambda: Transform.from_rotvec(Box((0.6, 0.4, 0.3)), (0.3, -0.5, 0.2), (0.05, -0.02, 0.1))
    _add("box.camera.32x32", lambda: (box(), *_cam(32)), ("camera", "quick"),
         "rotated, translated box seen by a 32×32 camera at distance 3")

    def _box_parallel():
        rng = np.random.default_rng(14)
        n = 512
        axis = rng.integers(0, 3, n)
        d = np.eye(3)[axis] * rng.choice([-1.0, 1.0], n)[:, None]
        o = rng.uniform(-0.9, 0.9, size=(n, 3))
        off = np.where(np.arange(n) % 2 == 0, 1e-9, -1e-9)  # just outside / just inside a face plane
        other = (axis + 1 + rng.integers(0, 2, n)) % 3
        o[np.arange(n), other] = np.sign(rng.uniform(-1, 1, n)) * (1.0 + off)
        o[np.arange(n), axis] = -3.0 * d[np.arange(n), axis]
        return Box((1.0, 1.0, 1.0)), o, d

    _add("box.parallel", _box_parallel, ("parallel", "grazing", "stability"),
         "rays parallel to the faces of the unit-half-size box, 1e-9 outside (miss) or inside (hit) a face plane")
    _add("box.inside", lambda: (Box((1.0, 0.5, 0.25)), *_rays.in_ball(256, 0.24, seed=15)), ("inside",),
         "origins inside a box, random directions")
    _add("box.thinplate.1e-6", lambda: (Box((1.0, 1.0, 1e-6)), *_cam(32, eye=(0.5, 1.0, 2.5))), ("thin", "camera"),
         "a plate 2e-6 thick seen obliquely by a 32×32 camera")

    # torus ----------------------------------------------------------------------------------
    _add("torus.camera.32x32", lambda: (Torus(1.0, 0.25), *_cam(32, eye=(0.0, -2.5, 1.8))), ("camera", "quick"),
         "torus R = 1, r = 0.25 seen obliquely by a 32×32 camera")
    for n in LARGE_SIZES:
        _add(f"torus.camera.{n}x{n}", lambda n=n: (Torus(1.0, 0.25), *_cam(n, eye=(0.0, -2.5, 1.8))), large_tags(n),
             f"torus R = 1, r = 0.25 seen obliquely by a {n}×{n} camera (the 32×32 view at scale)", scene=Torus(1.0, 0.25))

    def _torus_grazing(k):
        rng = np.random.default_rng(20 + k)
        n = 256
        y = (1.25) * (1 + np.where(np.arange(n) % 2 == 0, 1.0, -1.0) * 10.0 ** (-k))
        phase = rng.uniform(0, 2 * np.pi, n)
        c, s = np.cos(phase), np.sin(phase)
        # the ray along the tangent of the outer equator at angle `phase`, offset y from the axis
        o = np.stack([y * c + 3 * s, y * s - 3 * c, np.zeros(n)], axis=1)
        d = np.stack([-s, c, np.zeros(n)], axis=1)
        return Torus(1.0, 0.25), o, d

    for k in (3, 6, 9, 12):
        _add(f"torus.grazing.1e-{k}", lambda k=k: _torus_grazing(k), ("grazing",),
             f"rays in the equatorial plane passing (R + r)(1 ± 1e-{k}) from the axis: grazing the outer equator")

    def _torus_tangent():
        rng = np.random.default_rng(30)
        n = 256
        y0 = rng.uniform(-0.9, 0.9, n)
        o = np.stack([np.full(n, -3.0), y0, np.full(n, 0.25)], axis=1)
        d = np.tile([1.0, 0.0, 0.0], (n, 1))
        return Torus(1.0, 0.25), o, d

    _add("torus.tangent", _torus_tangent, ("tangent", "grazing", "stability"),
         "rays in the plane z = r touching the top of the tube at ρ = R: double roots of the quartic")
    for e in (3, 6):
        _add(f"torus.far.1e{e}", lambda e=e: (Torus(1.0, 0.25), *_rays.far(256, 10.0**e, 1.0, seed=40 + e)), ("far",),
             f"torus seen from distance 1e{e}", t_max=2 * 10.0**e)

    def _torus_inside():
        rng = np.random.default_rng(50)
        n = 256
        ang, v = rng.uniform(0, 2 * np.pi, n), rng.uniform(0, 2 * np.pi, n)
        rr = 0.2 * rng.uniform(size=n)
        rho = 1.0 + rr * np.cos(v)
        o = np.stack([rho * np.cos(ang), rho * np.sin(ang), rr * np.sin(v)], axis=1)
        return Torus(1.0, 0.25), o, _rays.random_directions(n, 51)

    _add("torus.inside", _torus_inside, ("inside",), "origins inside the tube, random directions")

    # capsule, cylinder ----------------------------------------------------------------------
    _add("capsule.camera.32x32",
         lambda: (Capsule((-0.5, -0.3, 0.1), (0.4, 0.5, -0.2), 0.35), *_cam(32)), ("camera",),
         "an oblique capsule seen by a 32×32 camera")
    cyl = lambda: Transform.from_rotvec(CappedCylinder(0.5, 0.7), (0.9, 0.0, 0.3))
    _add("cylinder.camera.32x32", lambda: (cyl(), *_cam(32)), ("camera",), "a tilted capped cylinder, 32×32 camera")

    def _cyl_parallel():
        rng = np.random.default_rng(60)
        n = 512
        xy = rng.uniform(-0.8, 0.8, size=(n, 2))
        o = np.concatenate([xy, np.full((n, 1), 3.0)], axis=1)
        return CappedCylinder(0.5, 0.7), o, np.tile([0.0, 0.0, -1.0], (n, 1))

    _add("cylinder.parallel", _cyl_parallel, ("parallel",),
         "rays parallel to the cylinder's axis: the cap or a miss (the quadratic degenerates)")

    # non-SDF implicits ----------------------------------------------------------------------
    _add("algsphere.camera.32x32", lambda: (AlgebraicSphere(domain_radius=6.5), *_cam(32)), ("camera", "quick"),
         "the lecture's |x|² − 1 (not an SDF, L = 13 on |x| ≤ 6.5) seen by a 32×32 camera; t ≤ 3.5 keeps "
         "rays in the domain", t_max=3.5)
    _add("ellipsoid.camera.32x32",
         lambda: (Transform.from_rotvec(Ellipsoid((1.0, 0.6, 0.4), domain_radius=6.5), (0.2, 0.7, 0.0)), *_cam(32)),
         ("camera",), "a rotated ellipsoid quadric (not an SDF), 32×32 camera", t_max=3.5)
    _add("scaled.torus.k3", lambda: (Scaled(Torus(1.0, 0.25), 3.0), *_cam(32, eye=(0.0, -2.5, 1.8))), ("camera",),
         "3 × the torus SDF: same surface, L = 3")

    # understated Lipschitz bound ------------------------------------------------------------
    def _understated():
        # 10 × a hollow ball (shell 0.9 ≤ |x| ≤ 1): true L = 10, declared 1.  From an origin in the
        # hollow (|o| ≤ 0.5), φ ≥ 10·0.4 = 4, so a step φ/L_declared ≥ 4 clears the whole ball
        # (radius 1) in one step: a method that trusts L returns a miss; every ray hits the
        # inner sphere at the closed-form exit of the hollow.
        o, d = _rays.in_ball(256, 0.5, seed=80)
        scene = DeclaredLipschitz(Scaled(Difference(Sphere(radius=1.0), Sphere(radius=0.9)), 10.0), 1.0)
        return scene, o, d

    _add("shell.understated.L10", _understated, ("understated", "stability"),
         "10 × a hollow ball's distance bound (true L = 10) declared with L = 1; origins in the hollow: "
         "every ray hits the inner sphere |x| = 0.9, a step of φ/1 jumps past the whole shell")

    # CSG ------------------------------------------------------------------------------------
    _add("csg.union.camera.32x32",
         lambda: (Union(Torus(1.0, 0.25), Box((0.4, 0.4, 0.4))), *_cam(32, eye=(0.0, -2.5, 1.8))),
         ("camera", "quick"), "torus ∪ box, 32×32 camera")
    for n in LARGE_SIZES:
        _add(f"csg.union.camera.{n}x{n}",
             lambda n=n: (Union(Torus(1.0, 0.25), Box((0.4, 0.4, 0.4))), *_cam(n, eye=(0.0, -2.5, 1.8))),
             large_tags(n), f"torus ∪ box, {n}×{n} camera (the 32×32 view at scale)",
             scene=Union(Torus(1.0, 0.25), Box((0.4, 0.4, 0.4))))
    _add("csg.difference.camera.32x32",
         lambda: (Difference(Box((0.7, 0.7, 0.7)), Sphere(radius=0.9)), *_cam(32, eye=(1.5, 1.2, 2.2))),
         ("camera",), "box minus a sphere (bites at the corners), 32×32 camera")
    _add("csg.intersection.camera.32x32",
         lambda: (Intersection(Sphere(radius=1.0), Transform.from_rotvec(Box((0.8, 0.8, 0.8)), (0.4, 0.4, 0.0))),
                  *_cam(32)), ("camera",), "sphere ∩ rotated box, 32×32 camera")
    _add("csg.complement.inside",
         lambda: (Complement(Sphere(radius=1.0)), *_rays.impact(256, np.linspace(0.0, 1.5, 256), 3.0, seed=70)),
         ("inside",), "the outside of the unit sphere as the solid: origins inside it at distance 3")
    _add("csg.shell.1e-4",
         lambda: (Difference(Sphere(radius=1.0), Sphere(radius=1.0 - 1e-4)), *_cam(32)), ("thin", "camera", "stability"),
         "a spherical shell 1e-4 thick (hollow ball), 32×32 camera")

    # fields without closed-form hits ----------------------------------------------------------
    from .mlp import MLPField
    from .numerical import CallableField

    _add("mlp.camera.32x32", lambda: (MLPField(), *_cam(32, fov=50.0)), ("camera", "mlp", "quick"),
         "the stored 3→16→16→1 MLP blob (Lipschitz bound ≈ 29.9) seen by a 32×32 camera; hits from the "
         "certified numerical reference", t_max=6.0)
    _add("callable.wavy.camera.32x32",
         lambda: (CallableField(wavy_sphere, lipschitz=1.25, name="reference.cases.wavy_sphere", smooth=True),
                  *_cam(32)),
         ("camera",), "a user callable |x| − 1 + 0.05 sin(5x)sin(5y)sin(5z), Lipschitz bound 1.25, declared "
         "smooth (its normals and curvatures judged against jax's autodiff of it)",
         t_max=6.0)


def wavy_sphere(x, xp):
    """A user-style callable field: |x| − 1 + 0.05 sin 5x sin 5y sin 5z.  The bump's gradient is
    0.25 (c₁s₂s₃, s₁c₂s₃, s₁s₂c₃) (sᵢ = sin 5xᵢ, cᵢ = cos 5xᵢ) whose squared norm
    Σ cᵢ² Πⱼ≠ᵢ sⱼ² ≤ 1 (with pᵢ = sᵢ², cᵢ² = 1 − pᵢ it is the probability that exactly two of three
    independent events of probabilities pᵢ occur), so L ≤ 1 + 0.25 = 1.25."""
    r = xp.sqrt(xp.sum(x * x, axis=-1))
    return r - 1.0 + 0.05 * xp.sin(5.0 * x[..., 0]) * xp.sin(5.0 * x[..., 1]) * xp.sin(5.0 * x[..., 2])


_register_all()
