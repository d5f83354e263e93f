"""Scene trees compiled to scalar numba functions φ(p, x, y, z) and their ray bounds.

:func:`compile_scene` walks a scene tree (:mod:`reference.scene`) and writes the Python source of
two functions, which numba compiles:

* ``phi(p, x0, x1, x2) -> φ`` — each node's ``_eval`` formula as scalar statements, in the order
  of operations the array code uses (``reference.arrays.norm`` is √((v₀² + v₁²) + v₂²), CSG a
  left fold of ``numpy.minimum``/``maximum`` with their NaN propagation, a rigid transform
  x' = (x − τ) R as Σᵢ (xᵢ − τᵢ) R_ij), so that φ agrees with numpy's to the last bit where numpy
  does not call BLAS (the transform's and the MLP's ``matmul`` sum in BLAS's order: there the
  two agree to rounding);
* ``bounds(p, o0, o1, o2, d0, d1, d2) -> (lo, hi)`` — the node's
  :meth:`reference.scene.Field.ray_bounds` (:mod:`reference.raybounds`: ball chords, slab tests,
  meets and hulls, padded alike).

Every number of the scene (parameters, centres, pads' sizes, a rotation, MLP weights) is read
from the float64 array ``p`` at a fixed index, so the source depends on the tree's *structure*
only: it is the cache key (:attr:`CompiledScene.key`), and scenes that differ in their numbers
alone share one compiled kernel.

Nodes compiled (exact types, so a subclass that changes a formula is not mistaken for its base):
Sphere, Plane, Box, Torus, Capsule, CappedCylinder, AlgebraicSphere, Ellipsoid, Scaled, Union,
Intersection, Difference, Complement, Transform, MLPField and the catalog's DeclaredLipschitz (a
child with another stated L, which the root finders read from ``scene.info``).  Any other node (a mesh, a grid, a
neural SDF with softplus layers, a user's callable or ``Field`` subclass) raises
:class:`impls.protocol.Declined` with the reason.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..protocol import Declined
from reference.csg import MANY_BOUNDS

EPS64 = float(np.finfo(np.float64).eps)
INV_MAX64 = 1.0 / float(np.finfo(np.float64).max)


@dataclasses.dataclass(frozen=True)
class CompiledScene:
    """A scene as source (``key``: the structure) and numbers (``params``: float64, read by index)."""

    key: str
    params: np.ndarray


def _known():
    from reference import (AlgebraicSphere, Box, CappedCylinder, Capsule, Complement, Difference, Ellipsoid,
                           Intersection, MLPField, Plane, Scaled, Sphere, Torus, Transform, Union)
    from reference.cases import DeclaredLipschitz

    return {Sphere: "sphere", Plane: "plane", Box: "box", Torus: "torus", Capsule: "capsule",
            CappedCylinder: "cylinder", AlgebraicSphere: "algsphere", Ellipsoid: "ellipsoid", Scaled: "scaled",
            Union: "union", Intersection: "intersection", Difference: "difference", Complement: "complement",
            Transform: "transform", MLPField: "mlp", DeclaredLipschitz: "declared"}


COMPILED_NODES = ("Sphere", "Plane", "Box", "Torus", "Capsule", "CappedCylinder", "AlgebraicSphere", "Ellipsoid",
                  "Scaled", "Union", "Intersection", "Difference", "Complement", "Transform", "MLPField",
                  "DeclaredLipschitz")


def decline_reason(scene) -> str | None:
    """Why ``scene`` cannot be compiled (the first node that is not one of :data:`COMPILED_NODES`,
    by exact type), or None."""
    known = _known()
    walk = getattr(scene, "walk", None)
    nodes = list(walk()) if callable(walk) else [scene]
    for node in nodes:
        if type(node) not in known:
            return (f"numba compiles scene trees of {', '.join(COMPILED_NODES)} nodes; "
                    f"{type(node).__name__} is none of them (its φ is not compiled)")
    return None


class _Writer:
    """Accumulates source lines, fresh local names and the parameter array."""

    def __init__(self):
        self.lines: list[str] = []
        self.params: list[float] = []
        self.n = 0

    def name(self, stem: str = "v") -> str:
        self.n += 1
        return f"{stem}{self.n}"

    def put(self, values) -> int:
        """Append float64 values to ``p``; returns the index of the first."""
        start = len(self.params)
        self.params.extend(float(v) for v in np.ravel(np.asarray(values, np.float64)))
        return start

    def ref(self, value) -> str:
        """A scalar of the scene as ``p[i]``."""
        return f"p[{self.put([value])}]"

    def let(self, expr: str, stem: str = "v") -> str:
        v = self.name(stem)
        self.lines.append(f"    {v} = {expr}")
        return v


# -- φ ------------------------------------------------------------------------------------------


def _norm(w: _Writer, v) -> str:
    """√((v₀² + v₁²) + v₂²) (reference.arrays.norm: sum_last folds left)."""
    return w.let("sqrt(" + _sum([f"{a} * {a}" for a in v]) + ")")


def _sum(terms) -> str:
    s = terms[0]
    for t in terms[1:]:
        s = f"({s}) + ({t})"
    return s


def _phi(w: _Writer, node, x) -> str:
    kind = _known()[type(node)]
    if kind == "sphere":
        c = [w.ref(v) for v in node.center]
        r = w.ref(node.radius)
        v = [w.let(f"{xi} - {ci}") for xi, ci in zip(x, c)]
        return w.let(f"{_norm(w, v)} - {r}")
    if kind == "algsphere":
        c = [w.ref(v) for v in node.center]
        r = w.ref(node.radius)
        v = [w.let(f"{xi} - {ci}") for xi, ci in zip(x, c)]
        return w.let(f"({_sum([f'{a} * {a}' for a in v])}) - {r} * {r}")
    if kind == "plane":
        h = w.ref(node.offset)
        n = [w.ref(v) for v in node.normal]
        return w.let(f"({_sum([f'{xi} * {ni}' for xi, ni in zip(x, n)])}) - {h}")
    if kind == "box":
        b = [w.ref(v) for v in node.half_size]
        q = [w.let(f"abs({xi}) - {bi}") for xi, bi in zip(x, b)]
        m = [w.let(f"_max({qi}, 0.0)") for qi in q]
        n = _norm(w, m)
        return w.let(f"{n} + _min(_max(_max({q[0]}, {q[1]}), {q[2]}), 0.0)")
    if kind == "torus":
        R, r = w.ref(node.major), w.ref(node.minor)
        rho = _norm(w, x[:2])
        a = w.let(f"{rho} - {R}")
        return w.let(f"sqrt({a} * {a} + {x[2]} * {x[2]}) - {r}")
    if kind == "capsule":
        a = [w.ref(v) for v in node.a]
        b = [w.ref(v) for v in node.b]
        r = w.ref(node.radius)
        pa = [w.let(f"{xi} - {ai}") for xi, ai in zip(x, a)]
        ba = [w.let(f"{bi} - {ai}") for bi, ai in zip(b, a)]
        h = w.let(f"({_sum([f'{u} * {v}' for u, v in zip(pa, ba)])}) / ({_sum([f'{v} * {v}' for v in ba])})")
        h = w.let(f"_min(_max({h}, 0.0), 1.0)")
        q = [w.let(f"{u} - {h} * {v}") for u, v in zip(pa, ba)]
        return w.let(f"{_norm(w, q)} - {r}")
    if kind == "cylinder":
        r, hh = w.ref(node.radius), w.ref(node.half_height)
        w0 = w.let(f"{_norm(w, x[:2])} - {r}")
        w1 = w.let(f"abs({x[2]}) - {hh}")
        m = [w.let(f"_max({wi}, 0.0)") for wi in (w0, w1)]
        n = _norm(w, m)
        return w.let(f"{n} + _min(_max({w0}, {w1}), 0.0)")
    if kind == "ellipsoid":
        a = [w.ref(v) for v in node.axes]
        y = [w.let(f"{xi} / {ai}") for xi, ai in zip(x, a)]
        return w.let(f"({_sum([f'{v} * {v}' for v in y])}) - 1.0")
    if kind == "declared":  # the child's φ; only the stated L differs (the root finders read it from info)
        return _phi(w, node.child, x)
    if kind == "scaled":
        k = w.ref(node.scale)
        return w.let(f"{k} * {_phi(w, node.child, x)}")
    if kind in ("union", "intersection"):
        op = "_min" if kind == "union" else "_max"
        out = _phi(w, node.children[0], x)
        for c in node.children[1:]:
            out = w.let(f"{op}({out}, {_phi(w, c, x)})")
        return out
    if kind == "difference":
        a, b = node.children
        fa = _phi(w, a, x)
        fb = _phi(w, b, x)
        return w.let(f"_max({fa}, -{fb})")
    if kind == "complement":
        return w.let(f"-{_phi(w, node.child, x)}")
    if kind == "transform":
        tau = [w.ref(v) for v in node.translation]
        R = node.rotation
        i0 = w.put(R)  # row-major: R[i, j] at i0 + 3 i + j
        u = [w.let(f"{xi} - {ti}") for xi, ti in zip(x, tau)]
        y = tuple(w.let(_sum([f"{u[i]} * p[{i0 + 3 * i + j}]" for i in range(3)])) for j in range(3))
        return _phi(w, node.child, y)
    if kind == "mlp":
        W = node.weights
        h1, h2 = W["W1"].shape[1], W["W2"].shape[1]
        offs = [w.put(W[k]) for k in ("W1", "b1", "W2", "b2", "W3", "b3")]
        return w.let(f"_mlp(p, {', '.join(map(str, offs))}, {h1}, {h2}, {x[0]}, {x[1]}, {x[2]})")
    raise Declined(f"numba: no φ for {type(node).__name__}")  # pragma: no cover - decline_reason screens


# -- ray bounds (reference.raybounds) -----------------------------------------------------------


def _ball(w: _Writer, o, d, centre, radius) -> tuple[str, str]:
    c = [w.ref(v) for v in np.asarray(centre, np.float64)]
    R = w.ref(radius)
    pad_lin = w.ref(1e-6 * float(radius))
    lo, hi = w.name("lo"), w.name("hi")
    w.lines.append(f"    {lo}, {hi} = _ball_chord({', '.join(o)}, {', '.join(d)}, {', '.join(c)}, {R}, {pad_lin})")
    return lo, hi


def _box(w: _Writer, o, d, half, size) -> tuple[str, str]:
    b = [w.ref(v) for v in half]
    S = w.ref(size)
    pad_lin = w.ref(1e-6 * float(size))
    lo, hi = w.name("lo"), w.name("hi")
    w.lines.append(f"    {lo}, {hi} = _box_chord({', '.join(o)}, {', '.join(d)}, {', '.join(b)}, {S}, {pad_lin})")
    return lo, hi


def _unbounded(w: _Writer) -> tuple[str, str]:
    return w.let("-inf", "lo"), w.let("inf", "hi")


def _meet(w: _Writer, *bs) -> tuple[str, str]:
    lo, hi = bs[0]
    for a, b in bs[1:]:
        lo, hi = w.let(f"_max({lo}, {a})", "lo"), w.let(f"_min({hi}, {b})", "hi")
    none = w.let(f"not ({lo} <= {hi})", "e")
    return w.let(f"inf if {none} else {lo}", "lo"), w.let(f"-inf if {none} else {hi}", "hi")


def _hull(w: _Writer, *bs) -> tuple[str, str]:
    lo, hi = bs[0]
    for a, b in bs[1:]:
        lo, hi = w.let(f"_min({lo}, {a})", "lo"), w.let(f"_max({hi}, {b})", "hi")
    return lo, hi


def _bounds(w: _Writer, node, o, d) -> tuple[str, str]:
    kind = _known()[type(node)]
    if kind in ("sphere", "algsphere", "capsule", "plane", "mlp", "complement"):  # Field.ray_bounds: the ball
        ball = node.bounding_sphere()
        return _unbounded(w) if ball is None else _ball(w, o, d, ball[0], float(ball[1]))
    if kind == "box":
        return _box(w, o, d, node.half_size, node.bounding_sphere()[1])
    if kind == "cylinder":
        r, h = node.radius, node.half_height
        return _box(w, o, d, (r, r, h), node.bounding_sphere()[1])
    if kind == "ellipsoid":  # as reference.implicits.Ellipsoid.ray_bounds
        box, r = _box(w, o, d, node.axes, max(node.axes)), node.search_radius()
        return box if r is None else _meet(w, box, _ball(w, o, d, (0.0, 0.0, 0.0), r))
    if kind == "torus":
        size = node.major + node.minor
        ball = _ball(w, o, d, (0.0, 0.0, 0.0), size)
        lo, hi = w.name("lo"), w.name("hi")
        w.lines.append(f"    {lo}, {hi} = _slab_chord({o[2]}, {d[2]}, {w.ref(node.minor)}, "
                       f"_pad({', '.join(o)}, {w.ref(size)}, {w.ref(1e-6 * size)}))")
        return _meet(w, ball, (lo, hi))
    if kind in ("scaled", "declared"):
        return _bounds(w, node.child, o, d)
    if kind == "union":
        kids = node.operands()
        if len(kids) < MANY_BOUNDS:
            return _hull(w, *(_bounds(w, c, o, d) for c in node.children))
        # as reference.csg.Union.ray_bounds: many operands, those with a ball bounded by its chord
        balls = [c.bounding_sphere() for c in kids]
        return _hull(w, *(_bounds(w, c, o, d) for c, b in zip(kids, balls) if b is None),
                     *(_ball(w, o, d, b[0], float(b[1])) for b in balls if b is not None))
    if kind == "intersection":
        return _meet(w, *(_bounds(w, c, o, d) for c in node.children))
    if kind == "difference":  # Intersection(a, Complement(b)): a's bound met with the whole line
        return _meet(w, _bounds(w, node.children[0], o, d), _unbounded(w))
    if kind == "transform":
        tau = [w.ref(v) for v in node.translation]
        i0 = w.put(node.rotation)
        u = [w.let(f"{oi} - {ti}") for oi, ti in zip(o, tau)]
        o2 = tuple(w.let(_sum([f"{u[i]} * p[{i0 + 3 * i + j}]" for i in range(3)])) for j in range(3))
        d2 = tuple(w.let(_sum([f"{d[i]} * p[{i0 + 3 * i + j}]" for i in range(3)])) for j in range(3))
        return _bounds(w, node.child, o2, d2)
    raise Declined(f"numba: no ray bounds for {type(node).__name__}")  # pragma: no cover


def compile_scene(scene) -> CompiledScene:
    """The source of ``phi`` and ``bounds`` for ``scene`` (module docstring) and its numbers;
    :class:`impls.protocol.Declined` for a scene with a node numba does not compile."""
    reason = decline_reason(scene)
    if reason:
        raise Declined(reason)
    w = _Writer()
    f = _phi(w, scene, ("x0", "x1", "x2"))
    src = ["def phi(p, x0, x1, x2):", *w.lines, f"    return {f}", ""]
    w.lines = []
    lo, hi = _bounds(w, scene, ("o0", "o1", "o2"), ("d0", "d1", "d2"))
    src += ["def bounds(p, o0, o1, o2, d0, d1, d2):", *w.lines, f"    return {lo}, {hi}", ""]
    return CompiledScene(key="\n".join(src), params=np.asarray(w.params, np.float64))


# -- the helpers the generated source calls (compiled by numba alongside it) ---------------------


def helpers():
    """``{name: jitted function}`` for the generated source's namespace (built on first use, so
    that importing this module does not import numba)."""
    global _HELPERS
    if _HELPERS is None:
        _HELPERS = _make_helpers()
    return _HELPERS


_HELPERS = None


def _make_helpers():
    from numba import njit

    jit = njit(error_model="numpy")

    @jit
    def _max(a, b):
        """numpy.maximum: NaN if either is NaN, else the larger (a on a tie)."""
        return a if (a >= b or a != a) else b

    @jit
    def _min(a, b):
        """numpy.minimum: NaN if either is NaN, else the smaller (a on a tie)."""
        return a if (a <= b or a != a) else b

    @jit
    def _pad(o0, o1, o2, size, pad_lin):
        """reference.raybounds.pad: 1e-6·size + 32ε(|o| + size) (1e-6·size precomputed)."""
        return pad_lin + 32.0 * EPS64 * (math.sqrt((o0 * o0 + o1 * o1) + o2 * o2) + size)

    @jit
    def _ball_chord(o0, o1, o2, d0, d1, d2, c0, c1, c2, radius, pad_lin):
        """reference.raybounds.ball_chord."""
        w0, w1, w2 = c0 - o0, c1 - o1, c2 - o2
        tc = (w0 * d0 + w1 * d1) + w2 * d2
        p0, p1, p2 = w0 - tc * d0, w1 - tc * d1, w2 - tc * d2
        rad = radius + _pad(w0, w1, w2, radius, pad_lin)
        q = rad * rad - ((p0 * p0 + p1 * p1) + p2 * p2)
        if q >= 0:
            half = math.sqrt(q)
            return tc - half, tc + half
        return math.inf, -math.inf

    @jit
    def _slab_chord(oa, da, half_width, padding):
        """reference.raybounds.slab_chord (with the padding given)."""
        h = half_width + padding
        aoa = abs(oa)
        if abs(da) < (aoa + h) * INV_MAX64:  # parallel, or crossings beyond the largest float
            whole = math.inf if aoa <= h else -math.inf
            return -whole, whole
        t1, t2 = (-h - oa) / da, (h - oa) / da
        return _min(t1, t2), _max(t1, t2)

    @jit
    def _box_chord(o0, o1, o2, d0, d1, d2, b0, b1, b2, size, pad_lin):
        """reference.raybounds.box_chord: three slabs, one pad, met."""
        padding = _pad(o0, o1, o2, size, pad_lin)
        lo, hi = _slab_chord(o0, d0, b0, padding)
        a, b = _slab_chord(o1, d1, b1, padding)
        lo, hi = _max(lo, a), _min(hi, b)
        a, b = _slab_chord(o2, d2, b2, padding)
        lo, hi = _max(lo, a), _min(hi, b)
        if not (lo <= hi):
            return math.inf, -math.inf
        return lo, hi

    @njit(error_model="numpy")
    def _mlp(p, oW1, ob1, oW2, ob2, oW3, ob3, h1, h2, x0, x1, x2):
        """reference.mlp.MLPField: σ(σ(x W1 + b1) W2 + b2) W3 + b3, σ(z) = z/√(1 + z²); each
        product summed over its inner index in order, then the bias added."""
        a1 = np.empty(h1)
        for j in range(h1):
            a1[j] = (x0 * p[oW1 + j] + x1 * p[oW1 + h1 + j]) + x2 * p[oW1 + 2 * h1 + j]
        for j in range(h1):
            z = a1[j] + p[ob1 + j]
            a1[j] = z / math.sqrt(1.0 + z * z)
        z2 = np.zeros(h2)
        for i in range(h1):
            ai = a1[i]
            row = oW2 + i * h2
            for j in range(h2):
                z2[j] += ai * p[row + j]
        s = 0.0
        for j in range(h2):
            z = z2[j] + p[ob2 + j]
            s += (z / math.sqrt(1.0 + z * z)) * p[oW3 + j]
        return s + p[ob3]

    return {"_max": _max, "_min": _min, "_pad": _pad, "_ball_chord": _ball_chord, "_slab_chord": _slab_chord,
            "_box_chord": _box_chord, "_mlp": _mlp, "sqrt": math.sqrt, "inf": math.inf}


def scene_functions(compiled: CompiledScene):
    """``(phi, bounds)``: the generated source compiled by numba (LLVM inlines them into the root finders)."""
    from numba import njit

    ns = dict(helpers())
    exec(compile(compiled.key, "<isobench numba scene>", "exec"), ns)  # noqa: S102 - our own generated source
    jit = njit(error_model="numpy")
    return jit(ns["phi"]), jit(ns["bounds"])
