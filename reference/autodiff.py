"""Derivatives of a user's field by automatic differentiation, the reference for its normals,
curvatures and hit-depth derivatives (:class:`reference.numerical.CallableField` with
``smooth=True``; dt/dθ = −(∂φ/∂θ)/⟨∇φ, d⟩ with θ its ``params``, lecture eq. 7–8).

A user's φ is code, not a formula: no closed form of ∇φ, ∂φ/∂θ or the Hessian exists to write down.
Reverse-mode autodiff of the same code (jax, float64) gives the derivatives *of the computed
expression*, each elementary operation differentiated exactly and rounded once: the result is
the true derivative to a few ulps times the expression's condition, with no truncation error — a
finite difference would trade a truncation error O(h²) against a rounding error O(ε/h) and is
what the numpy backend itself is checked for.  jax is used (not torch) because its ``vmap`` of
``hessian`` gives every point's 3×3 Hessian in one compiled program.

What is checked, not trusted: the user's ``fn`` must trace under ``jax.numpy`` and give there the
values it gives under numpy (a function that branches on its namespace, or calls numpy on the
points, would otherwise be differentiated as another function); every derivative must be finite
on the surface (elsewhere, at a singular point of φ such as |x − c| at c, it is left NaN, as the
closed forms leave it).
A failure is a :class:`NotImplementedError` naming the fix, which a case turns into a skipped
row with that reason (:class:`reference.cases.NoExactAnswer`).

Accuracy (tests/test_reference_autodiff.py): against the closed forms of the sphere, ellipsoid and
torus written as user functions, normals within 1e-14 rad and principal curvatures within
1e-12 relative on points of their surfaces; the torus's dt/d(R, r) within 1e-12 relative.
"""

from __future__ import annotations

import functools
from typing import Any, Callable

import numpy as np

#: |φ_jax − φ_numpy| allowed at a point, relative to the terms' magnitude (|φ| + 1): the two
#: libraries round sin, exp, sqrt … differently by a few ulps, not by more
AGREE_RTOL = 1e-12

#: |φ| ≤ SURFACE_BAND·(1 + |x|∞): a point on the surface, where a non-finite derivative is an error
SURFACE_BAND = 1e-8

#: points per compiled call (the Hessian's intermediates are a few dozen arrays of this length)
CHUNK = 1 << 16


def _jax():
    try:
        import jax
        import jax.numpy as jnp
    except ImportError as exc:  # the reference needs jax only for this
        raise NotImplementedError(f"the derivatives of a user's field come from jax's autodiff, and jax is not "
                                  f"installed ({exc}); pip install jax") from None
    return jax, jnp


def _build(fn: Callable[..., Any], with_theta: bool):
    jax, jnp = _jax()

    def scalar(p, th):  # one point (3,) → φ (), through the batch interface the user wrote fn for
        v = fn(p[None, :], jnp) if th is None else fn(p[None, :], jnp, th)
        return jnp.reshape(v, (-1,))[0]

    # φ, ∇φ (and ∂φ/∂θ) in one program (one dispatch a call), the Hessian in another
    if with_theta:
        first = jax.vmap(jax.value_and_grad(scalar, argnums=(0, 1)), in_axes=(0, None))
    else:
        first = jax.vmap(lambda p: jax.value_and_grad(scalar)(p, None))
    hess = jax.vmap(jax.hessian(scalar), in_axes=(0, None)) if with_theta else jax.vmap(
        lambda p: jax.hessian(scalar)(p, None))
    return jax.jit(first), jax.jit(hess)


@functools.lru_cache(maxsize=64)
def _programs_cached(fn, with_theta: bool):
    return _build(fn, with_theta)


def _programs(fn: Callable[..., Any], with_theta: bool):
    """The jitted (values and derivatives, Hessians) of ``fn``, one pair per function: the
    rendering reference asks for ∇φ along its rays hundreds of times, and a fresh ``jax.jit``
    would trace and compile each call anew."""
    try:
        return _programs_cached(fn, with_theta)
    except TypeError:  # an unhashable callable object: built per call
        return _build(fn, with_theta)


#: the smallest batch: the rendering reference's adaptive quadrature asks for ∇φ at a few
#: points a call, thousands of times
MIN_ROWS = 64


def _rows(m: int) -> int:
    """Rows a batch of ``m`` points runs as: the next power of two of at least :data:`MIN_ROWS`
    (at most :data:`CHUNK`), so that the callers' many batch sizes share a few compiled shapes."""
    return min(CHUNK, 1 << (max(m, MIN_ROWS) - 1).bit_length())


def derivatives(fn: Callable[..., Any], x: np.ndarray, phi: np.ndarray, label: str, hessian: bool = False,
                theta=None):
    """``(∇φ (n, 3), H (n, 3, 3) or None, ∂φ/∂θ (n, P) or None)`` of ``fn(x, xp)`` — or, with
    ``theta`` (P,), of ``fn(x, xp, theta)`` — at points ``x`` (n, 3), float64, by jax's
    reverse-mode autodiff (H: the Hessian in x); ``phi`` (n,) is φ there as numpy computes it (the
    caller's checked evaluation, which jax's values must match); ``label`` names the field in errors.  Raises
    NotImplementedError where jax is missing, ``fn`` does not trace under ``jax.numpy``, gives
    other values there than under numpy, or has a non-finite derivative at a point."""
    x = np.ascontiguousarray(x, dtype=np.float64)
    th = None if theta is None else np.ascontiguousarray(theta, dtype=np.float64)
    jax, _ = _jax()
    first, hessians = _programs(fn, th is not None)
    g_parts, h_parts, v_parts, t_parts = [], [], [], []
    with jax.enable_x64(True):
        try:
            for s in range(0, x.shape[0], CHUNK):
                xc = x[s:s + CHUNK]
                m = xc.shape[0]
                # padding rows repeat the first point; their results are dropped (a float64 numpy
                # array goes to the program as it is: jnp.asarray first costs ~100 µs a call,
                # which the rendering reference pays tens of thousands of times)
                xc = np.concatenate([xc, np.repeat(xc[:1], _rows(m) - m, axis=0)])
                if th is None:
                    v, g = first(xc)
                else:
                    v, (g, dt) = first(xc, th)
                    t_parts.append(np.asarray(dt, np.float64)[:m])
                v_parts.append(np.asarray(v, np.float64)[:m])
                g_parts.append(np.asarray(g, np.float64)[:m])
                if hessian:
                    h = hessians(xc) if th is None else hessians(xc, th)
                    h_parts.append(np.asarray(h, np.float64)[:m])
        except Exception as exc:  # whatever the user's code raises under a tracer
            call = "fn(x, xp)" if th is None else "fn(x, xp, theta)"
            raise NotImplementedError(
                f"{label}: its derivatives come from jax's autodiff of {call} with xp = jax.numpy, and that "
                f"failed ({type(exc).__name__}: {str(exc).splitlines()[0][:200]}); compute with the namespace xp "
                "fn is given, or build the case without smooth=True") from None
    v = np.concatenate(v_parts) if v_parts else np.zeros(0)
    g = np.concatenate(g_parts) if g_parts else np.zeros((0, 3))
    h = (np.concatenate(h_parts) if h_parts else np.zeros((0, 3, 3))) if hessian else None
    dth = None if th is None else (np.concatenate(t_parts) if t_parts else np.zeros((0, th.size)))
    v_np = np.asarray(phi, np.float64).reshape(-1)
    off = np.abs(v - v_np) > AGREE_RTOL * (np.abs(v_np) + 1.0)
    if off.any():
        i = int(np.argmax(off))
        call = "fn(x, xp)" if th is None else "fn(x, xp, theta)"
        raise NotImplementedError(f"{label}: {call} gives other values under jax.numpy than under numpy "
                                  f"({v[i]!r} against {v_np[i]!r} at x = {x[i].tolist()}), so jax's derivatives "
                                  "would be another function's; compute with the namespace xp fn is given")
    bad = ~np.isfinite(g).all(axis=1) | (~np.isfinite(h).all(axis=(1, 2)) if hessian else False)
    if dth is not None:
        bad = bad | ~np.isfinite(dth).all(axis=1)
    # on the surface (where the normals, curvatures and dt/dθ are asked for) a derivative that is
    # not finite refutes the declaration; away from it (the rendering reference samples whole rays)
    # it is a singular point of φ, such as |x − c| at its centre, left NaN as the closed forms leave it
    near = bad & (np.abs(v_np) <= SURFACE_BAND * (1.0 + np.max(np.abs(x), axis=1)))
    if np.any(near):
        i = int(np.argmax(near))
        raise NotImplementedError(f"{label}: its derivative is not finite at x = {x[i].tolist()} on its surface "
                                  "(declared smooth=True: φ must be C² near its surface)")
    return g, h, dth
