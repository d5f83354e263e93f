"""isobench reference: exact scenes, exact answers and the case catalog (float64 truth).

Nothing here imports a backend or the bench runner.
"""

from .cases import Case, catalog, get_case
from .primitives import Sphere
from .scene import Field, SceneInfo

__all__ = ["Case", "Field", "SceneInfo", "Sphere", "catalog", "get_case"]
