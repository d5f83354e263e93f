"""Scene trees: the one description of geometry that every backend evaluates.

A scene is an immutable tree of :class:`Field` nodes (primitives, CSG, transforms, MLP fields,
user callables).  Every node evaluates its implicit function φ(x) written against the *array
API* (https://data-apis.org/array-api/), so numpy, torch and jax evaluate the very same formula
with their own arrays: a backend passes its namespace ``xp`` (``numpy``,
``array_api_compat.torch``, ``jax.numpy``) and its arrays.

Conventions (used everywhere in isobench):

* Points are arrays of shape ``(..., 3)``; φ returns shape ``(...)``.
* φ < 0 inside, φ > 0 outside, φ = 0 on the surface (the lecture's Ω⁻ / Ω⁺ / ∂Ω).
* Parameters.  Each node owns a tuple of named float64 parameters (``own_params``).  The
  scene's parameter vector θ is their concatenation in *pre-order* (node, then its children
  left to right).  ``value(x, xp, theta)`` evaluates φ with θ replaced by an array of the
  caller's library, which is how backends differentiate φ with respect to θ (dt/dθ).

Exact answers (ray intervals, normals, curvatures, closest points, dt/dθ) live on the nodes
too, in float64 numpy only, because they are the reference and nothing else needs them.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import hashlib
import json
import math
from typing import Any, Iterator

import numpy as np

from .arrays import (  # noqa: F401  (re-exported: the names' old home, still imported from here)
    _CONSTS,
    _CONSTS_MAX,
    _array_lib,
    _const,
    _fold_last,
    _is_real_floating,
    const,
    max_last,
    norm,
    safe_norm,
    sum_last,
    unit,
)
from . import intervals as iv
from .code_digest import function_digest
from .raybounds import ball_chord, unbounded_like


@dataclasses.dataclass(frozen=True)
class SceneInfo:
    """What a scene states about itself; the planner decides what to run from this.

    exact_sdf:      φ is the exact signed distance (|∇φ| = 1 a.e.).
    lipschitz:      a valid Lipschitz constant L of φ on the domain of interest (|φ(x) − φ(y)|
                    ≤ L|x − y|), or ``None`` when no bound is known.  Sphere tracing steps φ/L.
    distance_bound: φ is an SDF *bound* (|φ| ≤ distance, same sign), as CSG of SDFs is.
    smooth:         φ is C² away from a measure-zero set at distance > 0 from typical hits.
    exact_hits:     ray–surface intervals are known in closed form (``ray_intervals``).
    exact_normals:  ``normal_exact`` is available.
    exact_curvature: ``curvatures_exact`` is available.
    exact_hit_param_grad: ``hit_param_grad`` (dt/dθ) is available in closed form.
    domain:         where ``lipschitz`` holds when it is not all of ℝ³ (e.g. "|x| ≤ 4"); ``None``
                    means everywhere.
    """

    exact_sdf: bool
    lipschitz: float | None
    distance_bound: bool
    smooth: bool
    exact_hits: bool
    exact_normals: bool
    exact_curvature: bool
    exact_hit_param_grad: bool
    domain: str | None = None


class ParamCursor:
    """Hands out each node's parameters in pre-order, as constants or as slices of θ.

    ``xp`` is the caller's array namespace and ``like`` an array whose dtype and device the
    parameters take.  With ``theta=None`` the stored float64 values are converted; otherwise
    consecutive slices of ``theta`` (shape ``(P,)``) are returned, so autodiff flows to θ.
    """

    def __init__(self, xp: Any, like: Any, theta: Any | None = None):
        self.xp = xp
        self.like = like
        self.theta = theta
        self.offset = 0

    def take(self, value: np.ndarray) -> Any:
        value = np.asarray(value, dtype=np.float64)
        if self.theta is None:
            return _const(self.xp, self.like, value)
        n = value.size
        piece = self.theta[self.offset : self.offset + n]
        self.offset += n
        return piece[0] if value.ndim == 0 else self.xp.reshape(piece, value.shape)


class Field:
    """Base class of every scene node.

    Subclasses define ``own_params`` (name → float64 array, the differentiable parameters),
    ``children`` and ``_eval(x, xp, cursor)``; they override ``info`` and whichever exact
    answers they know.  Nodes are immutable: build a new node to change a parameter.
    """

    #: short lowercase name used in case ids and reports
    kind: str = "field"
    #: whether ``info.lipschitz`` is a claim the node takes on trust (a user's field, a declared
    #: bound) rather than one its construction proves; a node class defined outside ``reference``
    #: counts as declaring whatever this says (:func:`impls.core.methods_root.checks_inside`)
    declares_lipschitz: bool = False

    def __deepcopy__(self, memo):
        """A deep copy without the node's derived caches (``functools.cached_property`` values: a
        mesh's AABB tree, a network's stacked weights), which the copy builds again on demand: they
        follow from the node's fields, and some (libigl's AABB) cannot be copied.  The runner
        gives a plug-in backend such a copy (``bench.run.configuration.own_copy``)."""
        cls = type(self)
        new = cls.__new__(cls)
        memo[id(self)] = new
        cached = {name for klass in cls.__mro__ for name, v in vars(klass).items()
                  if isinstance(v, functools.cached_property)}
        for k, v in vars(self).items():
            if k not in cached:
                object.__setattr__(new, k, copy.deepcopy(v, memo))
        return new

    # -- structure -------------------------------------------------------------------------
    def own_params(self) -> dict[str, np.ndarray]:
        return {}

    @property
    def children(self) -> tuple["Field", ...]:
        return ()

    @property
    def info(self) -> SceneInfo:  # pragma: no cover - every concrete node overrides
        raise NotImplementedError

    def walk(self) -> Iterator["Field"]:
        """Nodes in pre-order (the order of θ)."""
        yield self
        for c in self.children:
            yield from c.walk()

    # -- parameters ------------------------------------------------------------------------
    def param_vector(self) -> np.ndarray:
        """θ: all differentiable parameters in pre-order, float64, shape ``(P,)``."""
        parts = [np.ravel(np.asarray(v, np.float64)) for n in self.walk() for v in n.own_params().values()]
        return np.concatenate(parts) if parts else np.zeros(0)

    def param_names(self) -> list[str]:
        """One dotted name per entry of θ: ``<preorder index>.<kind>.<param>[<i>]``."""
        names = []
        for k, node in enumerate(self.walk()):
            for pname, v in node.own_params().items():
                v = np.asarray(v)
                if v.ndim == 0:
                    names.append(f"{k}.{node.kind}.{pname}")
                else:
                    names.extend(f"{k}.{node.kind}.{pname}[{i}]" for i in range(v.size))
        return names

    def with_params(self, theta: np.ndarray) -> "Field":
        """A copy of the scene with θ (in :meth:`param_vector` order) replaced: how the exact
        answers are differentiated by finite differences, and how a fitted θ is turned back
        into a scene."""
        theta = np.asarray(theta, np.float64)
        if theta.shape != self.param_vector().shape:
            raise ValueError(f"theta must have shape {self.param_vector().shape} (scene.param_vector()), got {theta.shape}")
        node, used = self._with_params(theta, 0)
        return node

    def _with_params(self, theta: np.ndarray, offset: int) -> tuple["Field", int]:
        own = {}
        for name, v in self.own_params().items():
            v = np.asarray(v, np.float64)
            piece = theta[offset : offset + v.size]
            offset += v.size
            own[name] = float(piece[0]) if v.ndim == 0 else tuple(piece.tolist())
        kids = []
        for c in self.children:
            c2, offset = c._with_params(theta, offset)
            kids.append(c2)
        return self._rebuild(own, tuple(kids)), offset

    def _rebuild(self, own: dict, children: tuple) -> "Field":
        """A node like this one with own parameters ``own`` and ``children`` (dataclass nodes:
        ``dataclasses.replace``; other nodes override)."""
        if dataclasses.is_dataclass(self):
            extra = {"child": children[0]} if children else {}
            return dataclasses.replace(self, **own, **extra)
        raise NotImplementedError(f"{type(self).__name__} cannot rebuild itself with new parameters")

    # -- evaluation ------------------------------------------------------------------------
    def value(self, x: Any, xp: Any = np, theta: Any | None = None) -> Any:
        """φ(x; θ) for points ``x`` of shape ``(..., 3)`` in the caller's library ``xp``.

        The result is checked once per call (:func:`check_field_output`): an array of ``x``'s
        library and floating dtype with shape ``x.shape[:-1]``, else a :class:`FieldError` naming
        the field — a wrong shape would otherwise be broadcast against the rays silently."""
        if theta is not None:
            n_params = self.param_vector().size
            if tuple(theta.shape) != (n_params,):
                raise ValueError(
                    f"theta has shape {tuple(theta.shape)} but the scene has {n_params} parameters; "
                    "pass scene.param_vector() (or an array of the same length)"
                )
        return check_field_output(self, x, self._eval(x, xp, ParamCursor(xp, x, theta)), xp)

    def __call__(self, x: Any, xp: Any = np, theta: Any | None = None) -> Any:
        return self.value(x, xp, theta)

    def _eval(self, x: Any, xp: Any, cursor: ParamCursor) -> Any:  # pragma: no cover
        raise NotImplementedError

    # -- rounding ----------------------------------------------------------------------------
    @property
    def rounding_gain(self) -> float:
        """How many times the generic rounding of φ this node's evaluation may carry (≥ 1).

        The Lipschitz check (:func:`impls.core.rootfind.lipschitz_violated`) allows φ a rounding
        of 16ε per unit of the magnitudes involved (|x|, |φ|, the scene's extent), which covers
        distances to centres and planes, CSG min/max and affine layers.  A node whose φ rounds
        worse states how much worse here; a scene's gain is the largest of its nodes'
        (:func:`impls.core.methods_root.rounding_gain`).  Default 1."""
        return 1.0

    # -- bounds ------------------------------------------------------------------------------
    def domain_hulls(self) -> tuple["Field", "Field"] | None:
        """For a node whose Lipschitz bound holds on a domain only (``info.domain``), two exact
        SDFs of convex sets, ``(inner, outer)``: ``inner`` contains every point where φ ≤ 0 and
        lies strictly inside ``outer``, and ``outer`` lies inside the domain; ``None`` where no
        such pair is known (the default; always for a bound that holds everywhere).

        With them the root finders' step field bounds the node everywhere
        (:func:`impls.core.methods_root.step_field`): max(min(φ/L, −d_outer), d_inner) has φ's
        sign, and is 1-Lipschitz on all of ℝ³ while φ is L-Lipschitz on ``outer``.  The pair is
        that of the stored parameters."""
        return None

    def bounding_sphere(self) -> tuple[np.ndarray, float] | None:
        """A ball ``(centre (3,), radius)`` that contains every point where φ ≤ 0, or ``None``
        when the solid is unbounded or no such ball is known (the default).

        Outside the ball φ > 0, so a ray has no surface crossing outside it: the default
        :meth:`ray_bounds`, to which the root finders clip each ray's search interval
        (:func:`impls.core.rootfind.clip_to_bounds`), is its chord.  The ball is that of the
        stored parameters (not of a θ passed to ``value``).  Composite nodes combine their children's balls:
        union → a ball enclosing all, intersection → the smallest, difference → the first
        operand's, complement → ``None``; a rigid transform moves the centre."""
        return None

    def ray_bounds(self, xp: Any, o: Any, d: Any) -> tuple[Any, Any]:
        """Per ray o + t d (rows of ``o``, ``d``; |d| = 1), arrays ``(lo, hi)`` such that every t
        with φ(o + t d) ≤ 0 lies in [lo, hi] (+inf, −inf: none; −inf, +inf: no bound), for the
        stored parameters, computed with ``xp`` (:mod:`reference.raybounds`; padded against
        rounding).  The root finders search only inside it.

        Default: the chord of :meth:`bounding_sphere`, or the whole line without one.  Nodes
        that know more override it: a box is its slab test, a torus a ball ∩ slab, a union the
        hull of its children's bounds (so a ray between two far-apart children that misses
        both is a miss), an intersection their overlap, a transform its child's in local
        coordinates."""
        ball = self.bounding_sphere()
        if ball is None:
            return unbounded_like(xp, o)
        return ball_chord(xp, o, d, ball[0], float(ball[1]))

    # -- exact answers (float64 numpy; override where known) -------------------------------
    def ray_intervals(self, o: np.ndarray, d: np.ndarray) -> list[np.ndarray]:
        """Per ray, the sorted boundaries of {t ∈ ℝ : φ(o + t d) < 0} as an array of shape
        ``(2k,)`` (enter, exit, enter, exit, …; ±inf allowed).  Rays are rows of ``o``, ``d``.
        A node overrides this or :meth:`ray_interval_batch` (either gives the other)."""
        if type(self).ray_interval_batch is Field.ray_interval_batch:
            raise NotImplementedError(f"{type(self).__name__} has no exact ray intervals")
        return iv.batch_to_list(self.ray_interval_batch(o, d))

    def ray_interval_batch(self, o: np.ndarray, d: np.ndarray) -> iv.IntervalBatch:
        """The sets of :meth:`ray_intervals`, all rays at once (:class:`reference.intervals.IntervalBatch`):
        the form CSG combines them in, one vectorised operation per node.  Default: from
        :meth:`ray_intervals`."""
        if type(self).ray_intervals is Field.ray_intervals:
            raise NotImplementedError(f"{type(self).__name__} has no exact ray intervals")
        return iv.batch_from_list(self.ray_intervals(o, d))

    def first_hit(self, o: np.ndarray, d: np.ndarray, t_min: float = 0.0) -> np.ndarray:
        """Exact depth of the first crossing of φ = 0 at t > t_min along o + t d (inf: miss).
        Default: from :meth:`ray_interval_batch` (:func:`reference.intervals.batch_first_crossing`,
        the rule of :func:`first_hit_from_intervals`); primitives override with a vectorised formula.
        Sphere and torus also count a tangent touch (a double root, φ = 0 without a
        sign change) as a hit; interval-based first hits (CSG) do not, since a touch bounds no
        interval — a measure-zero set of rays."""
        return iv.batch_first_crossing(self.ray_interval_batch(o, d), t_min)

    def certified_roots(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Per ray (rows of ``o``, ``d``): True where exact (rational) arithmetic on the float64
        inputs proves that φ has a real root on the ray's line although float64 φ shows no sign
        change near it — a tangent or near-tangent ray, whose closed-form depth is then judged with
        the window bound of :func:`reference.depthbound.depth_bounds` instead of flagged.
        Default: nothing proven (all False); the sphere and the torus override it."""
        return np.zeros(np.shape(o)[0], bool)

    def jet(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Exact first-order jet at points ``x`` (n, 3), float64 numpy:
        ``(φ (n,), ∇ₓφ (n, 3), ∂φ/∂θ (n, P))`` with θ in :meth:`param_vector` order.

        Closed-form derivatives of each node's formula (no differencing); at a kink (CSG seam,
        box edge, medial axis) it returns one of the one-sided derivatives."""
        x = _points(x)
        phi, grad, dtheta = self._jet(x)
        return phi, grad, dtheta

    def _jet(self, x: np.ndarray):
        raise NotImplementedError(f"{type(self).__name__} has no closed-form derivatives")

    def normal_exact(self, x: np.ndarray) -> np.ndarray:
        """Outward unit normal n = ∇φ/|∇φ| (lecture, "Properties - Normal") at points ``x``."""
        return unit(self.jet(x)[1])

    def curvatures_exact(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Principal curvatures (κ1 ≥ κ2) at surface points, sign convention: positive where
        the surface bends away from its outward normal (a sphere has κ = +1/r).  See
        :mod:`reference.curvature` for the mean, sum and Gaussian curvature."""
        raise NotImplementedError(f"{type(self).__name__} has no exact curvature")

    def closest_point_exact(self, x: np.ndarray) -> np.ndarray:
        """Closest surface point x* = x − φ(x) ∇φ(x) (exact for an exact SDF, where |∇φ| = 1
        and the segment from x to x* is normal to the surface; off the medial axis, where the
        closest point is unique).  Raises for scenes that are not exact SDFs."""
        if not self.info.exact_sdf:
            raise ValueError(
                f"{type(self).__name__} is not an exact SDF, so x − φ∇φ is not its closest point; "
                "closest points are only provided for exact SDFs"
            )
        x = _points(x)
        phi, grad, _ = self.jet(x)
        return x - phi[:, None] * grad

    def hit_param_grad(self, o: np.ndarray, d: np.ndarray, t: np.ndarray) -> np.ndarray:
        """dt/dθ at the hits x = o + t d, shape (n, P) in :meth:`param_vector` order.

        Implicit differentiation of φ(o + t(θ) d; θ) = 0 (lecture eq. 7–8):
        dt/dθ = −(∂φ/∂θ) / ⟨∇ₓφ, d⟩, evaluated with the closed-form partials of :meth:`jet`.
        Rows of missed rays (t = inf) are NaN."""
        o, d = _points(o, "o"), _points(d, "d")
        t = np.asarray(t, np.float64)
        hit = np.isfinite(t)
        out = np.full((o.shape[0], self.param_vector().size), np.nan)
        if hit.any():
            x = o[hit] + t[hit, None] * d[hit]
            _, grad, dtheta = self.jet(x)
            gd = np.einsum("ij,ij->i", grad, d[hit])
            out[hit] = -dtheta / gd[:, None]
        return out

    # -- identity ----------------------------------------------------------------------------
    def spec(self) -> dict:
        """A JSON-able description; equal specs mean equal scenes (used for the case hash)."""
        return {
            "kind": self.kind,
            "type": type(self).__name__,
            "params": {k: np.asarray(v, np.float64).tolist() for k, v in self.own_params().items()},
            "children": [c.spec() for c in self.children],
            **({"static": st} if (st := self._static_spec()) else {}),
            # a user's node class: its code, which the package's source digests do not cover
            **({"code": function_digest(type(self))} if user_defined(self) else {}),
        }

    def _static_spec(self) -> dict:
        """Fixed (non-parameter) settings that change the scene, e.g. a plane's normal."""
        if not dataclasses.is_dataclass(self):
            return {}
        params = self.own_params()
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.name not in params and not isinstance(v, Field):
                out[f.name] = np.asarray(v, np.float64).tolist()
        return out

    def content_hash(self) -> str:
        return hashlib.sha256(json.dumps(self.spec(), sort_keys=True).encode()).hexdigest()[:12]


def user_defined(node: Any) -> bool:
    """Whether scene node ``node`` is of a class defined outside ``reference`` (a user's ``Field``
    subclass): code whose bound and content isobench cannot vouch for."""
    return not type(node).__module__.startswith("reference.")


class FieldError(ValueError):
    """A scene's field did not return φ of the points it was given (wrong shape, dtype or array
    library), or raised while evaluating; the message names the field and the fix."""


def field_label(field: Any) -> str:
    """How error messages name a field: its ``name`` (user fields) and its class."""
    name = getattr(field, "name", None)
    return f"scene field {name!r} ({type(field).__name__})" if name else f"scene field {type(field).__name__}"


#: what a φ of the wrong kind is told to do (check_field_output)
_PHI_FIXES = {
    "lib": "(e.g. xp.sqrt(xp.sum(x * x, axis=-1)), not np.linalg.norm) and keep one value per point",
    "shape": "A result of another shape would be broadcast against the rays (e.g. every ray given ray 0's value): "
             "reduce over the last axis only, without keepdims or indexing such as [..., :1]",
    "dtype": "φ must be real and floating (cast with xp.astype(phi, x.dtype); take the real part only if it is meant)",
}


def check_field_output(field: Any, x: Any, out: Any, xp: Any = None) -> Any:
    """``out`` if it is a valid φ of the points ``x`` (shape ``(..., 3)``): an array of ``x``'s
    library (numpy, torch, jax, …), shape ``x.shape[:-1]`` and ``x``'s dtype.  A real floating
    result of another precision is converted to ``x``'s dtype (the loops carry one dtype);
    anything else is a :class:`FieldError` naming the field, what it returned and what was
    expected (:func:`check_point_output`)."""
    return check_point_output(field_label(field), x, out, "φ", (), "one value per point", _PHI_FIXES)


def check_point_output(label: str, x: Any, out: Any, what: str, tail: tuple, per_point: str, fixes: dict) -> Any:
    """``out`` if it is a valid per-point output of the points ``x`` (shape ``(..., 3)``): an array
    of ``x``'s library, shape ``x.shape[:-1] + tail`` and ``x``'s dtype; a real floating result of
    another precision is converted to ``x``'s dtype.  Anything else is a :class:`FieldError`
    naming ``label`` (the field: a scene's φ, a colour field's ρ), what it returned, what was
    expected (``what`` of that shape, ``per_point``) and the fix (``fixes``: ``lib``, ``shape``,
    ``dtype``).

    Cost: the common valid case is three attribute comparisons per call, no pass over the data;
    under ``jax.jit`` the check runs once, at trace time, where shapes and dtypes are static."""
    try:
        if type(out) is type(x) and out.shape == x.shape[:-1] + tail and out.dtype == x.dtype:
            return out
        xs, xd = tuple(x.shape), x.dtype
    except AttributeError:
        if not hasattr(x, "shape"):  # points that are not an array: nothing to compare against
            return out
        xs, xd = tuple(x.shape), x.dtype
    want = xs[:-1] + tuple(tail)
    lib_x = _array_lib(x)
    shape = "x.shape[:-1]" + (f" + {tuple(tail)}" if tail else "")
    expected = f"expected {what} of shape {shape} = {want} ({per_point}), a real floating {lib_x} array like x (dtype {xd})"
    where = f"{label} was given points x of shape {xs} ({lib_x}, dtype {xd})"
    lib_out = _array_lib(out)
    if lib_out != lib_x or not hasattr(out, "shape"):
        if isinstance(out, (int, float, complex, bool)) or (lib_out == "numpy" and np.ndim(out) == 0 and lib_x != "numpy"):
            got = f"a scalar {type(out).__name__}"
        else:
            got = f"a {type(out).__module__.split('.')[0]} {type(out).__name__}"
        raise FieldError(f"{where} and returned {got}; {expected}. Compute with the namespace xp the field is given "
                         f"{fixes['lib']}")
    if tuple(out.shape) != want:
        raise FieldError(f"{where} and returned shape {tuple(out.shape)}; {expected}. {fixes['shape']}")
    if out.dtype == xd:
        return out
    if not _is_real_floating(out):
        raise FieldError(f"{where} and returned dtype {out.dtype}; {expected}. {fixes['dtype']}")
    return out.to(xd) if lib_x == "torch" else out.astype(xd)


def _points(x, name: str = "x") -> np.ndarray:
    a = np.asarray(x, np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must have shape (n, 3), got {a.shape}; reshape with {name}.reshape(-1, 3)")
    return a


def enclosing_ball(balls) -> tuple[np.ndarray, float] | None:
    """A ball containing every ball of ``balls`` (``None`` if any is ``None``): centred at the
    middle of their bounding box, radius max |cᵢ − c| + rᵢ (not the smallest such ball, which
    would need an iterative solver for a small gain in the clipped interval)."""
    balls = list(balls)
    if not balls or any(b is None for b in balls):
        return None
    cs = np.array([b[0] for b in balls], np.float64)
    rs = np.array([b[1] for b in balls], np.float64)
    c = 0.5 * ((cs - rs[:, None]).min(axis=0) + (cs + rs[:, None]).max(axis=0))
    return c, float(np.max(np.linalg.norm(cs - c, axis=1) + rs))


def first_hit_from_intervals(intervals: list[np.ndarray], t_min: float = 0.0) -> np.ndarray:
    """First surface crossing at t > t_min (strictly after the start) from ray intervals.

    A boundary is a crossing of φ = 0.  The first boundary greater than ``t_min`` is the first
    hit whether the ray starts outside (an entry) or inside (an exit).  ``inf`` means a miss.
    """
    out = np.full(len(intervals), math.inf)
    for i, b in enumerate(intervals):
        b = b[np.isfinite(b) & (b > t_min)]
        if b.size:
            out[i] = b.min()
    return out
