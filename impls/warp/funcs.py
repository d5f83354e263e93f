"""Warp functions the generated scene source calls (:mod:`impls.warp.fields`).

numpy's ``minimum``/``maximum`` semantics (NaN if either argument is NaN, else the smaller or
larger, the first on a tie), as :func:`impls.numba.fields.helpers` writes them for numba: a CSG
node's φ is a fold of these, so the NaN propagation must match numpy's for the statuses to.
"""

import warp as wp


@wp.func
def _max(a: wp.float64, b: wp.float64) -> wp.float64:
    """numpy.maximum: NaN if either is NaN, else the larger (a on a tie)."""
    if a >= b or a != a:
        return a
    return b


@wp.func
def _min(a: wp.float64, b: wp.float64) -> wp.float64:
    """numpy.minimum: NaN if either is NaN, else the smaller (a on a tie)."""
    if a <= b or a != a:
        return a
    return b
