"""Embree as an engine backend: ``raycast`` on triangle meshes with Intel Embree 4 through embreex.

A plug-in, registered as a third party would register one (``pyproject.toml``:
``[project.entry-points."isobench.backends"] embree = "impls.embree.backend:EmbreeBackend"``,
installed by the extra ``engines``).  Without embreex installed, loading it raises an ImportError
whose message is the install command, which the registry reports as the reason the backend is
unavailable.

What it computes: ``embreex.rtcore_scene.EmbreeScene.run(origins, directions, output=1)`` (one
``rtcIntersect1`` per ray, in embreex's loop: one thread), the first hit of each float32 ray with
the mesh's float32 triangles: ``tfar`` (the depth; a ray that hits nothing keeps embreex's default
``tfar`` and ``primID = -1``), ``Ng`` (Embree's unnormalised geometric normal: for faces listed
counter-clockwise seen from outside, as isobench's meshes are, it points outward).  Embree's
ray–triangle test is its watertight float32 test (Woop, Benthin & Wald, JCGT 2013); how far its
answer is from the exact one is what isobench measures.  The contract every engine follows
(statuses, outputs, ``[t_min, t_max]``, the BVH build as ``compile_s``): :mod:`impls.engine`.
"""

from __future__ import annotations

import importlib.metadata

try:
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh
except ImportError as exc:  # the registry turns this into Unavailable(reason=…)
    raise ImportError("embreex is not installed: pip install -c constraints.txt -e '.[engines]'") from exc

import numpy as np

from ..engine import EngineBackend, engine_capabilities


class EmbreeBackend(EngineBackend):
    """``raycast`` with Embree (embreex) on triangle meshes, float32 (:mod:`impls.engine`)."""

    lib = "embree"
    capabilities = engine_capabilities((
        "Embree 4 through embreex: EmbreeScene.run(..., output=1), one rtcIntersect1 per ray in embreex's loop "
        "(one thread); normal: Embree's geometric normal Ng, normalised in float64",))

    def build(self, vertices: np.ndarray, faces: np.ndarray):
        scene = rtcore_scene.EmbreeScene()
        TriangleMesh(scene, vertices, faces)
        # Embree builds the BVH when the scene is first queried: one ray here, so that the build
        # is counted as the build (Prepared.compile_s) and not in the timed query
        scene.run(np.zeros((1, 3), np.float32), np.array([[1.0, 0.0, 0.0]], np.float32), output=1)
        return scene

    def cast(self, geometry, origins: np.ndarray, directions: np.ndarray):
        out = geometry.run(origins, directions, output=1)
        t = np.where(out["primID"] >= 0, out["tfar"], np.float32(np.inf))
        return t, out["Ng"]

    def versions(self) -> dict[str, str]:
        return {"embreex": importlib.metadata.version("embreex"), "numpy": np.__version__}
