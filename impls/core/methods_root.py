"""Build the root-finder state machine of a ``root``-family method from its validated knobs.

Each root method's :class:`impls.methods.MethodSpec` names its builder here (``spec.build``);
the knobs reach it complete (defaults are filled once, by ``MethodSpec.validate``), with the
loop driver's choice of ladder samples for the knob value -1."""

from __future__ import annotations

import math
import weakref

import numpy as np

from reference.csg import Complement, Difference, Intersection, Union
from reference.implicits import Scaled
from reference.scene import Field, user_defined
from reference.transform import Transform

from .chandrupatla import MarchChandrupatla
from .rootfind import REFINERS, Bisect, CertifiedStep, ConstantStep, MarchRefine, SphereTrace


#: scene → its step field (:func:`step_field`), computed once per scene object
_STEP_FIELDS: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()
_ITSELF = object()


def step_field(scene):
    """The field the certified root finders march on: the same surface as ``scene``, with each
    CSG operand's value divided by that operand's own Lipschitz bound, so that one steep operand
    no longer shortens every step (``scene`` itself, the very object, where that changes nothing).

    Math.  Let the scene be a tree of union (min), intersection (max), difference (max(a, −b)),
    complement (−), rigid transform and positive scaling k·φ over leaves φᵢ with bounds Lᵢ (every
    other node is a leaf).  Replace each leaf by (L*/Lᵢ)·φᵢ, L* = minᵢ Lᵢ, and drop the scalings.
    Each term (L*/Lᵢ)·φᵢ is L*-Lipschitz and has the sign of φᵢ; min, max, negation and rigid
    motions keep both, so the result s is L*-Lipschitz with sign(s) = sign(φ) everywhere: the
    same inside, outside and surface.  A step |s|/L* is therefore certified exactly as |φ|/L is,
    and is never shorter where the leaves' bounds differ: in a union of all-positive φᵢ it is
    minᵢ φᵢ/Lᵢ, where φ/maxᵢLᵢ was taken before (docs/methods.md, "Certified steps on CSG").
    Where every leaf's bound with the scalings above it is the same (one leaf; CSG of exact
    SDFs) s = φ·L*/L, and the scene is returned unchanged.  The bounds are the leaves' stated
    ones, so a leaf taking its bound on trust is checked as before: s is checked against L*
    along every ray, and a steeper leaf makes s steeper than L* there.

    A leaf whose bound Lᵢ holds on a domain only (``SceneInfo.domain``: the ellipsoid, the
    algebraic sphere, a neural SDF's local bound) is no bound on φᵢ beyond it, where φᵢ/Lᵢ can
    exceed the distance to the leaf: in a tree, where the ray bounds do not clip the search to
    the leaf's domain, its term (L*/Lᵢ)φᵢ, and φ/L itself, would certify steps across the leaf
    from outside (an algebraic sphere ∪ a floor 380 below it, seen from 20 above: φ/L steps
    50 across the sphere and 1,044 of 4,096 rays CONVERGED on the floor).  Such a leaf's term is
    L*·max(min(φᵢ/Lᵢ, −d_out), d_in), d_in and d_out the exact SDFs of its
    :meth:`reference.scene.Field.domain_hulls` (convex; d_in ≤ 0 wherever φᵢ ≤ 0, in strictly
    inside out, out inside the domain).  It has φᵢ's sign: where φᵢ < 0, d_in ≤ 0 and
    −d_out > 0; where φᵢ > 0 inside in, −d_out > 0 again; outside in, d_in > 0.  It is
    L*-Lipschitz on all of ℝ³: min(φᵢ/Lᵢ, −d_out) > d_in only on the convex set
    {d_in + d_out < 0} ⊆ out, where all three terms are 1-Lipschitz (×L*), and elsewhere the
    term is L*·d_in; the term is continuous, so a segment split at that set's boundary is
    L*-Lipschitz piece by piece.  Steps far from the leaf are distances to ``inner``; from a
    face of ``inner`` inwards the cap −d_out (≥ the gap between the hulls plus the depth) grows
    the step geometrically.  Every tree holding such a leaf is rewritten, whatever the bounds; a
    tree with a domain-bound leaf that states no hulls (a user's node) keeps φ/L, as before.

    Only the root finders' march and refinement read s, at the stored parameters: hits are the
    same zeros, and normals, shading and dt/dθ keep evaluating the scene (``ArrayBackend.solve``).
    The factors are :class:`reference.implicits.Scaled` nodes and the hulls spheres and boxes,
    which every backend compiles.  A leaf without a bound leaves the scene as it is (no step
    rule applies); so does a single leaf (its ray bounds lie inside any domain it states), unless
    a complement above it makes them the whole line."""
    try:
        got = _STEP_FIELDS.get(scene)
    except TypeError:  # not weak-referenceable: a user's object; computed each time
        got = None
    if got is None:
        got = _normalized(scene)
        try:
            # the scene itself is stored as a marker: a value referring to its key would keep it alive
            _STEP_FIELDS[scene] = _ITSELF if got is scene else got
        except TypeError:
            pass
    return scene if got is _ITSELF else got


#: the nodes the step field passes through (:func:`step_field`): sign-keeping combinations of their
#: children; every other node is a leaf
_COMBINATIONS = (Union, Intersection, Difference, Complement, Transform)


def _leaves(node, k: float, out: list) -> None:
    """(leaf, product of the scalings above it) of every leaf of ``node`` (:func:`step_field`)."""
    if type(node) is Scaled:
        _leaves(node.child, k * float(node.scale), out)
    elif type(node) in _COMBINATIONS:
        for c in node.children:
            _leaves(c, k, out)
    else:
        out.append((node, k))


def _times(node, k: float):
    """k·``node`` (``node`` itself for k = 1)."""
    return node if k == 1.0 else Scaled(child=node, scale=k)


def _hulls(leaf):
    """The leaf's :meth:`reference.scene.Field.domain_hulls` where its bound holds on a domain
    only (None: a user's node states none, its own call failed, or a hull is not a node stating
    an exact SDF, which the term's bound needs), else ()."""
    if getattr(leaf.info, "domain", None) is None:
        return ()
    try:
        got = leaf.domain_hulls()
        inner, outer = got
    except Exception:  # noqa: BLE001 - a user's node without the method, or a wrong answer: no hulls
        return None
    ok = all(isinstance(h, Field) and getattr(h.info, "exact_sdf", False) for h in (inner, outer))
    return (inner, outer) if ok else None


def _rebuild(node, lstar: float, hulls: dict):
    """``node`` with each leaf scaled by ``lstar`` over its bound (a domain-bound leaf bounded
    everywhere by its hulls, ``hulls``: id(leaf) → :func:`_hulls`) and the scalings dropped
    (:func:`step_field`); combinations are rebuilt by their own ``Field._rebuild``."""
    if type(node) is Scaled:
        return _rebuild(node.child, lstar, hulls)
    if type(node) in _COMBINATIONS:
        return node._rebuild(node.own_params(), tuple(_rebuild(c, lstar, hulls) for c in node.children))
    term = _times(node, lstar / float(node.info.lipschitz))
    if not hulls[id(node)]:
        return term
    inner, outer = hulls[id(node)]
    return Intersection(Union(term, _times(Complement(outer), lstar)), _times(inner, lstar))


def _normalized(scene):
    """The step field of ``scene`` (:func:`step_field`), built anew."""
    leaves: list = []
    _leaves(scene, 1.0, leaves)
    if not leaves:
        return scene
    try:
        bounds = [float(n.info.lipschitz) for n, _ in leaves]
    except Exception:  # noqa: BLE001 - a leaf without a numeric bound (None, a user's odd info): no step rule here
        return scene
    if not all(math.isfinite(b) and b > 0 for b in bounds):
        return scene
    hulls = {id(n): _hulls(n) for n, _ in leaves}
    if any(h is None for h in hulls.values()):
        # a domain-bound leaf without hulls: no term bounds it beyond its domain (docstring)
        return scene
    if any(hulls.values()):
        # a single leaf's own ray bounds keep the search inside its domain; a complement's (the
        # whole line) do not: from outside the domain φ/L steps across the leaf there too
        if len(leaves) == 1 and not any(type(n) is Complement for n in scene.walk()):
            return scene
    elif len({k * b for (_, k), b in zip(leaves, bounds)}) == 1:
        return scene
    return _rebuild(scene, min(bounds), hulls)


def lipschitz_step(scene) -> float:
    lip = scene.info.lipschitz
    if not lip:
        raise ValueError(f"{type(scene).__name__} states no Lipschitz bound; sphere tracing needs one")
    return 1.0 / float(lip)


def search_bounds(scene, knobs: dict, theta=None):
    """The scene whose ray bounds (:meth:`reference.scene.Field.ray_bounds`) the root finders
    clip rays to when knob ``bounds`` is on and φ is evaluated at the stored parameters (a θ
    passed in may move the surface out of the stored parameters' bounds), else None."""
    if not knobs["bounds"] or theta is not None:
        return None
    return scene


def rounding_scale(scene) -> float:
    """|centre| + radius of the scene's bounding ball (0 without one): the magnitude of φ's
    intermediates beyond the point itself, for the rounding slack of the Lipschitz check
    (:func:`impls.core.rootfind.lipschitz_violated`)."""
    ball = scene.bounding_sphere()
    if ball is None:
        return 0.0
    v = float(np.sqrt(np.sum(np.square(np.asarray(ball[0], np.float64))))) + float(ball[1])
    return v if math.isfinite(v) else 0.0


def rounding_gain(scene) -> float:
    """The largest :attr:`reference.scene.Field.rounding_gain` of the scene's nodes (≥ 1): the
    factor on the Lipschitz check's rounding slack for fields whose φ rounds worse than the
    generic bound (a mesh's closest point near skinny faces)."""
    gains = [float(getattr(n, "rounding_gain", 1.0)) for n in scene.walk()] if hasattr(scene, "walk") else []
    return max([1.0, *(g for g in gains if math.isfinite(g))])


def resolves(scene) -> bool:
    """Whether the scene's φ is a distance bound (an SDF, CSG of SDFs, a mesh's SDF), whose
    rounding near the surface the certified root finders model as L times the point's
    (:func:`impls.core.rootfind.resolution`); elsewhere only φ = 0 exactly is unresolved."""
    return bool(getattr(scene.info, "distance_bound", False) or getattr(scene.info, "exact_sdf", False))


def checks_inside(scene) -> bool:
    """Whether the certified root finders check the scene's Lipschitz bound inside every marching
    step (:func:`impls.core.rootfind.mid_probe`, one more evaluation per step): where some node
    takes its bound on trust (:attr:`reference.scene.Field.declares_lipschitz`: a user's
    :class:`reference.numerical.CallableField`, a :class:`reference.cases.DeclaredLipschitz`) or
    is a ``Field`` subclass defined outside ``reference``.  The library's own nodes (primitives,
    CSG, transforms, meshes, grids, the MLPs' spectral bounds) carry bounds proved by their
    construction and tested (tests/test_reference_bounds.py): their steps pay nothing for it."""
    nodes = scene.walk() if hasattr(scene, "walk") else (scene,)
    return any(getattr(n, "declares_lipschitz", False) or user_defined(n) for n in nodes)


def marching_check(scene, bounds, theta) -> float | None:
    """1/L for constant-step marching to check on its steps, or None: the scene declares a bound
    L, φ is evaluated at the stored parameters (the bound is theirs) and, for a bound stated on
    a domain only, the search is clipped to the ray bounds (marching does not rely on L, so it
    checks it only where the scene claims it)."""
    lip = scene.info.lipschitz
    if not lip or theta is not None or (getattr(scene.info, "domain", None) is not None and bounds is None):
        return None
    return 1.0 / float(lip)


def _ladder(knobs: dict, driver_ladder: int) -> int:
    """Ladder samples: the knob, or the driver's choice where the knob leaves it to the driver (-1)."""
    return driver_ladder if knobs["ladder"] == -1 else knobs["ladder"]


def build_sphere_trace(scene, t_min: float, t_max: float, knobs: dict, theta=None, *, ladder: int) -> SphereTrace:
    """``sphere_trace``'s algorithm from its validated knobs (:meth:`impls.methods.MethodSpec.validate`)."""
    return SphereTrace(inv_lip=lipschitz_step(scene), tol=knobs["tol"], max_steps=knobs["max_steps"],
                       omega=knobs["omega"], t_min=t_min, t_max=t_max, bounds=search_bounds(scene, knobs, theta),
                       probe=getattr(scene.info, "domain", None) is None, scale=rounding_scale(scene), gain=rounding_gain(scene),
                       resolve=resolves(scene), check_inside=checks_inside(scene))


def build_hybrid(scene, t_min: float, t_max: float, knobs: dict, theta=None, *, ladder: int,
                 refine: str = "secant") -> MarchRefine:
    """``hybrid_secant``'s (and ``render_surface``'s) algorithm from its validated knobs; the largest
    forced step is at least the smallest (``overstep`` below ``min_step`` means no forced-step
    range: the plain IDR march), clamped here only.  ``refine="chandrupatla"``: the same march,
    its brackets refined by scipy (``hybrid_chandrupatla``, :mod:`impls.core.chandrupatla`)."""
    rule = CertifiedStep(inv_lip=lipschitz_step(scene), min_step=knobs["min_step"],
                         overstep=max(knobs["overstep"], knobs["min_step"]), extrapolate=knobs["extrapolate"],
                         reach=knobs["reach"],
                         # a bound stated on a domain only (the algebraic sphere's on |x| ≤ R) is not
                         # checked past the ray bounds
                         probe=getattr(scene.info, "domain", None) is None)
    cls, refiner = (MarchChandrupatla, Bisect) if refine == "chandrupatla" else (MarchRefine, REFINERS[refine])
    return cls(rule=rule, refiner=refiner(), xtol=knobs["xtol"], max_steps=knobs["max_steps"],
                       t_min=t_min, t_max=t_max, bounds=search_bounds(scene, knobs, theta),
                       ladder=_ladder(knobs, ladder), ladder_after=knobs["ladder_after"],
                       scale=rounding_scale(scene), gain=rounding_gain(scene),
                       resolve=resolves(scene), check_inside=checks_inside(scene))


def build_hybrid_chandrupatla(scene, t_min: float, t_max: float, knobs: dict, theta=None, *, ladder: int):
    """``hybrid_chandrupatla``: ``hybrid_secant``'s certified march, then scipy's ``find_root``."""
    return build_hybrid(scene, t_min, t_max, knobs, theta, ladder=ladder, refine="chandrupatla")


def march_builder(refine: str):
    """The builder of ``march_<refine>``'s algorithm: constant steps, then ``refine`` (one of
    :data:`impls.core.rootfind.REFINERS`, or ``chandrupatla``: scipy's ``find_root`` on the brackets,
    :class:`impls.core.chandrupatla.MarchChandrupatla`)."""
    cls, refiner = (MarchChandrupatla, Bisect) if refine == "chandrupatla" else (MarchRefine, REFINERS[refine])

    def build_march(scene, t_min: float, t_max: float, knobs: dict, theta=None, *, ladder: int) -> MarchRefine:
        bounds = search_bounds(scene, knobs, theta)
        check = marching_check(scene, bounds, theta)
        # a MISS is certified by the samples' spheres only under a bound the scene declares and the
        # library proves (one taken on trust is checked at the steps' ends, not inside them)
        rule = ConstantStep(step=knobs["step"], check_inv_lip=check, cover=check is not None and not checks_inside(scene))
        return cls(rule=rule, refiner=refiner(), xtol=knobs["xtol"], max_steps=knobs["max_steps"], t_min=t_min,
                   t_max=t_max, bounds=bounds, ladder=_ladder(knobs, ladder), ladder_after=knobs["ladder_after"],
                   scale=rounding_scale(scene), gain=rounding_gain(scene), resolve=resolves(scene))

    build_march.__name__ = f"build_march_{refine}"
    return build_march


def root_impl(method: str):
    """The table entry of root method ``method``: the backend's :meth:`impls.base.ArrayBackend.solve`."""

    def impl(backend, scene, o, d, *, t_min, t_max, t_hit, **knobs):
        return backend.solve(method, scene, o, d, t_min=t_min, t_max=t_max, **knobs)

    impl.__name__ = method
    impl.__doc__ = f"{method} (see impls.core.rootfind and impls.methods.METHODS[{method!r}])."
    return impl
