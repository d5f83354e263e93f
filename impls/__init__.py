"""isobench backends: numpy/, torch/, jax/ mirror each other module for module and hold only
what differs between array libraries.

``backend.py`` is the library's hook object (:class:`impls.base.ArrayBackend`: arrays, device,
sync, compile, versions, and the hooks below); ``derivatives.py`` evaluates φ along rays with
dφ/dt, ∇φ and the Hessian at points, and Jacobians in θ (autodiff, or central differences in
numpy); ``driver.py`` runs a root finder's per-ray loop (active-set compaction in numpy and
torch, masked ``lax.while_loop`` levels in jax) with the backend's recorded ``settings``.  The
algorithms are in ``core/``, written once against the array API, and every backend runs the
same method table (``core/table.py``), built once from ``methods.py``, the method catalog (the
single source of methods, knobs and their defaults, requirements, outputs, and the builder of
each root finder).  ``protocol.py`` is the contract, ``registry.py`` finds backends (built-in,
entry points, ``module:attr``).
"""

from .methods import METHODS, get_method
from .protocol import Backend, Capabilities, Declined, Prepared, RayResult, Status
from .registry import Unavailable, available, default_ids, resolve

__all__ = ["METHODS", "Backend", "Capabilities", "Declined", "Prepared", "RayResult", "Status", "Unavailable",
           "available", "default_ids", "get_method", "resolve"]
