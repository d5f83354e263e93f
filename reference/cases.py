"""The case catalog: scenes × seeded ray families with stable dotted ids.

One catalog, imported by tests (``pytest`` ids) and by ``bench`` (report rows, baseline keys),
in the spirit of scipy's ``optimize/_tstutils.py``.  A case id is stable across versions
(``sphere.camera.64x64``); the case *version* is a content hash of everything that determines
its answers (scene spec, rays, search interval), so a baseline row is only compared with a row
of the same version.
"""

from __future__ import annotations

import dataclasses
import fnmatch
import functools
import hashlib
import json
from typing import Callable

import numpy as np

from . import rays as _rays
from .primitives import Sphere
from .scene import Field


@dataclasses.dataclass(frozen=True, eq=False)
class Case:
    """A scene plus a ray family and the search interval [t_min, t_max] along each ray.

    ``origins`` and ``directions`` are float64 ``(n, 3)``; directions are unit vectors.
    """

    id: str
    scene: Field
    origins: np.ndarray
    directions: np.ndarray
    t_min: float = 0.0
    t_max: float = 10.0
    tags: tuple[str, ...] = ()
    description: str = ""

    @property
    def n_rays(self) -> int:
        return int(self.origins.shape[0])

    @functools.cached_property
    def version(self) -> str:
        h = hashlib.sha256()
        h.update(json.dumps(self.scene.spec(), sort_keys=True).encode())
        h.update(np.ascontiguousarray(self.origins, np.float64).tobytes())
        h.update(np.ascontiguousarray(self.directions, np.float64).tobytes())
        h.update(repr((self.t_min, self.t_max)).encode())
        return h.hexdigest()[:12]

    @functools.cached_property
    def exact_t(self) -> np.ndarray:
        """Exact first-hit depth per ray in (t_min, t_max]; ``inf`` for a miss."""
        t = self.scene.first_hit(self.origins, self.directions, self.t_min)
        return np.where(t <= self.t_max, t, np.inf)


_FACTORIES: dict[str, Callable[[], Case]] = {}


def register(case_id: str):
    """Decorator adding a zero-argument case factory to the catalog under ``case_id``."""

    def deco(fn: Callable[[], Case]):
        if case_id in _FACTORIES:
            raise ValueError(f"duplicate case id {case_id!r}")
        _FACTORIES[case_id] = fn
        return fn

    return deco


@functools.cache
def get_case(case_id: str) -> Case:
    try:
        factory = _FACTORIES[case_id]
    except KeyError:
        raise KeyError(f"unknown case {case_id!r}; `python -m bench cases` lists them") from None
    case = factory()
    if case.id != case_id:
        raise AssertionError(f"factory for {case_id!r} built a case with id {case.id!r}")
    return case


def case_ids() -> list[str]:
    return sorted(_FACTORIES)


def catalog(pattern: str | None = None, tags: set[str] | None = None) -> list[Case]:
    """All cases whose id matches the glob ``pattern`` and that carry every tag in ``tags``."""
    out = []
    for cid in case_ids():
        if pattern and not any(fnmatch.fnmatchcase(cid, p) for p in pattern.split(",")):
            continue
        case = get_case(cid)
        if tags and not set(tags) <= set(case.tags):
            continue
        out.append(case)
    return out


# -- the cases -------------------------------------------------------------------------------


@register("sphere.camera.64x64")
def _sphere_camera() -> Case:
    origins, dirs = _rays.pinhole(eye=(0.0, 0.0, 3.0), look_at=(0.0, 0.0, 0.0), fov_deg=40.0, width=64, height=64)
    return Case(
        id="sphere.camera.64x64",
        scene=Sphere(),
        origins=origins,
        directions=dirs,
        t_min=0.0,
        t_max=10.0,
        tags=("quick", "camera", "sphere", "sdf"),
        description="unit sphere seen by a 64×64 pinhole camera at distance 3 (fov 40°); "
        "the corners miss",
    )
