"""isobench backends: numpy/, torch/, jax/ mirror each other module for module.

``backend.py`` wraps the library (arrays, device, sync, compile, versions); ``tracing.py`` holds
the ray root finders.  ``protocol.py`` is the contract, ``methods.py`` the method catalog,
``registry.py`` finds backends (built-in, entry points, ``module:attr``).
"""

from .methods import METHODS, get_method
from .protocol import Backend, Capabilities, Prepared, RayResult, Status
from .registry import Unavailable, available, default_ids, resolve

__all__ = ["METHODS", "Backend", "Capabilities", "Prepared", "RayResult", "Status", "Unavailable",
           "available", "default_ids", "get_method", "resolve"]
