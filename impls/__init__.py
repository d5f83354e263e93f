"""isobench backends: numpy/, torch/, jax/ mirror each other module for module.

``backend.py`` wraps the library (arrays, device, sync, compile, versions); ``tracing.py`` (root
finders: φ along rays and the loop driver), ``gradients.py`` (∇φ and the Hessian),
``param_grad.py`` (Jacobians in θ) and ``rendering.py`` bind the algorithms of ``core/`` —
written once against the array API — to the library.  ``protocol.py`` is the contract,
``methods.py`` the method catalog (the single source of methods, knobs, requirements and
outputs), ``registry.py`` finds backends (built-in, entry points, ``module:attr``).
"""

from .methods import METHODS, get_method
from .protocol import Backend, Capabilities, Prepared, RayResult, Status
from .registry import Unavailable, available, default_ids, resolve

__all__ = ["METHODS", "Backend", "Capabilities", "Prepared", "RayResult", "Status", "Unavailable",
           "available", "default_ids", "get_method", "resolve"]
