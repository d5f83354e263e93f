"""The method table of every array-library backend, built once from the method catalog.

Each entry is ``impl(backend, scene, o, d, *, t_min, t_max, t_hit, **knobs)`` (plus ``color=``
for methods with ``MethodSpec.needs_color``), written once in :mod:`impls.core` against the
backend's hooks (:class:`impls.base.ArrayBackend`): root finders run ``backend.solve``,
normals and curvature ``backend.grad_hess``, dt/dθ also ``backend.theta_jacobian``, renderers
both.  A method added to :data:`impls.methods.METHODS` with an implementation here is run by
every backend.
"""

from __future__ import annotations

from types import MappingProxyType

from ..methods import METHODS, MethodSpec
from . import param_grad, pointwise, rendering
from .methods_root import root_impl

_BY_FAMILY = {"gradient": pointwise.IMPLS, "param_grad": param_grad.IMPLS, "render": rendering.IMPLS}


def _impl(spec: MethodSpec):
    if spec.family == "root":
        return root_impl(spec.name)
    try:
        return _BY_FAMILY[spec.family][spec.name]
    except KeyError:
        raise LookupError(f"method {spec.name!r} ({spec.family}) is in the catalog but has no implementation "
                          "in impls.core") from None


#: ``{method name: impl}`` for every method of the catalog
METHOD_TABLE = MappingProxyType({name: _impl(spec) for name, spec in METHODS.items()})
