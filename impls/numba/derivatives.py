"""φ and dφ/dt along a ray in compiled code, as numpy's backend computes them.

``ev(p, o, d, t)`` = φ(o + t d) (x = o + t·d per coordinate, as numpy's ``o + t[:, None] * d``);
``ev_d`` also returns dφ/dt = ⟨∇φ, d⟩ as numpy's central difference
(:func:`impls.numpy.derivatives.ray_eval`): h = ε^{1/3}·max(1, |t|), rounded to a step exactly
representable at t (h ← (t + h) − t, ε^{1/3} where that is not > 0), and
(φ(x + h d) − φ(x − h d))/2h — error O(h²|φ‴|) + O(ε|φ|/h), about 1e-10 relative; 3 evaluations.
numba has no autodiff; this is the derivative Newton's refinement (``march_newton``) uses.
"""

from __future__ import annotations



import numpy as np

CBRT_EPS64 = float(np.cbrt(np.finfo(np.float64).eps))


def make_ray_eval(phi):
    """``(ev, ev_d)`` for the compiled scene function ``phi(p, x0, x1, x2)``."""
    from numba import njit

    from .fields import helpers

    _max = helpers()["_max"]
    jit = njit(error_model="numpy")

    def ev(p, o0, o1, o2, d0, d1, d2, t):
        return phi(p, o0 + t * d0, o1 + t * d1, o2 + t * d2)

    def ev_d(p, o0, o1, o2, d0, d1, d2, t):
        x0, x1, x2 = o0 + t * d0, o1 + t * d1, o2 + t * d2
        h = CBRT_EPS64 * _max(1.0, abs(t))
        h = (t + h) - t
        if not (h > 0):
            h = CBRT_EPS64
        f = phi(p, x0, x1, x2)
        fp = phi(p, x0 + h * d0, x1 + h * d1, x2 + h * d2)
        fm = phi(p, x0 - h * d0, x1 - h * d1, x2 - h * d2)
        return f, (fp - fm) / (2 * h)

    # Named after φ's module, not this one.  numba names compiled code by module, qualified name
    # and a counter that is per process, and links the code it loads from its disk cache by those
    # names: two scenes' ev_d, compiled by two processes with the same counter value, had one
    # name, and a process that loaded both kernels ran the first scene's φ in the second's
    # (tests/test_compile_cache.py).  φ's module is the scene structure's own
    # (:func:`impls.numba.driver.kernels_source`), so the names now differ wherever φ does.
    module = getattr(getattr(phi, "py_func", phi), "__module__", None) or __name__
    for f in (ev, ev_d):
        f.__module__ = module
    return jit(ev), jit(ev_d)



