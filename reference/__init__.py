"""isobench reference: exact scenes, exact answers and the case catalog (float64 truth).

Nothing here imports a backend or the bench runner.

Scenes: :class:`Sphere`, :class:`Plane`, :class:`Box`, :class:`Torus`, :class:`Capsule`,
:class:`CappedCylinder` (exact SDFs); :class:`AlgebraicSphere`, :class:`Ellipsoid`,
:class:`Scaled` (implicit, not SDFs, with Lipschitz bounds on a stated domain); :class:`Union`,
:class:`Intersection`, :class:`Difference`, :class:`Complement` (CSG); :class:`Transform`
(rigid placement); :class:`MLPField` (stored weights); :class:`NeuralSDF` (a trained softplus MLP
fitted to a mesh's SDF, with certified spectral and local Lipschitz bounds); :class:`CallableField` (user functions);
:class:`MeshSDF` (a closed triangle mesh, signed distance by libigl); :class:`GridSDF` (samples on
a regular grid, trilinear).  Importing the package registers every built-in case, the mesh and
grid cases included (:mod:`reference.mesh_cases`, :mod:`reference.grid`), and the neural SDF's
(:mod:`reference.neural_cases`).
"""

from .cases import Case, NoExactAnswer, case_ids, catalog, get_case, make_case, register, register_cases, register_each
from .csg import Complement, Difference, Intersection, Union
from .grid import GridSDF
from .implicits import AlgebraicSphere, Ellipsoid, Scaled
from .mesh import MeshSDF
from .mesh_cases import mesh_cases  # noqa: F401  (registers the mesh cases)
from .mlp import MLPField
from .neural import NeuralSDF
from .neural_cases import neural_cases  # noqa: F401  (registers the neural SDF cases)
from .numerical import CallableField, crossings_numeric, first_hit_numeric
from .primitives import Box, CappedCylinder, Capsule, Plane, Sphere, Torus
from .scene import Field, SceneInfo
from .transform import Transform

__all__ = [
    "AlgebraicSphere", "Box", "CallableField", "CappedCylinder", "Capsule", "Case", "Complement", "Difference",
    "Ellipsoid", "Field", "GridSDF", "MeshSDF", "Intersection", "MLPField", "NeuralSDF", "NoExactAnswer", "Plane", "Scaled", "SceneInfo", "Sphere", "Torus",
    "Transform", "Union", "case_ids", "catalog", "crossings_numeric", "first_hit_numeric", "get_case", "make_case", "register",
    "register_cases",
    "register_each",
]
