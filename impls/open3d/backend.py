"""Open3D as an engine backend: ``raycast`` on triangle meshes with ``open3d.t.geometry.RaycastingScene``.

A plug-in, registered as a third party would register one (``pyproject.toml``:
``[project.entry-points."isobench.backends"] open3d = "impls.open3d.backend:Open3DBackend"``,
installed by the extra ``engines``; Open3D's wheel also needs Debian's ``libusb-1.0-0``).  Without
open3d importable, loading it raises an ImportError whose message is the install command (and
the import's own error), which the registry reports as the reason the backend is unavailable.

What it computes: ``RaycastingScene.cast_rays`` on an (n, 6) float32 tensor ``[o, d]``, the first
hit of each ray with the mesh's float32 triangles (Open3D builds an Embree scene underneath):
``t_hit`` (the depth in units of ‖d‖ = 1; ``inf`` on a miss) and ``primitive_normals`` (the hit
triangle's unit normal).  ``nthreads``: the run's thread count (``OMP_NUM_THREADS``, which
``bench`` sets from ``--threads``), else Open3D's own choice.  The contract every engine follows
(statuses, outputs, ``[t_min, t_max]``, the scene build as ``compile_s``): :mod:`impls.engine`.
"""

from __future__ import annotations

import os

try:
    import open3d
except ImportError as exc:  # the registry turns this into Unavailable(reason=…)
    raise ImportError(f"open3d is not importable ({exc}): pip install -c constraints.txt -e '.[engines]' "
                      "(and Debian's libusb-1.0-0: apt-get install -y libusb-1.0-0)") from exc

import numpy as np

from ..engine import EngineBackend, engine_capabilities


def _threads() -> int:
    """The run's thread count (``OMP_NUM_THREADS``), 0 (Open3D decides) when unset or not a count."""
    try:
        return max(int(os.environ.get("OMP_NUM_THREADS", "0")), 0)
    except ValueError:
        return 0


class Open3DBackend(EngineBackend):
    """``raycast`` with Open3D's RaycastingScene on triangle meshes, float32 (:mod:`impls.engine`)."""

    lib = "open3d"
    capabilities = engine_capabilities((
        "Open3D RaycastingScene.cast_rays (an Embree scene inside Open3D) with nthreads = the run's --threads; "
        "normal: Open3D's primitive_normals",))

    def build(self, vertices: np.ndarray, faces: np.ndarray):
        o3c = open3d.core
        scene = open3d.t.geometry.RaycastingScene(nthreads=_threads())
        scene.add_triangles(o3c.Tensor(vertices, dtype=o3c.float32), o3c.Tensor(faces.astype(np.uint32),
                                                                                 dtype=o3c.uint32))
        # the BVH is built on the first query: one ray here, so that the build is counted as the
        # build (Prepared.compile_s) and not in the timed query
        scene.cast_rays(o3c.Tensor(np.array([[0, 0, 0, 1, 0, 0]], np.float32)), nthreads=_threads())
        return scene

    def cast(self, geometry, origins: np.ndarray, directions: np.ndarray):
        rays = open3d.core.Tensor(np.concatenate([origins, directions], axis=1))
        out = geometry.cast_rays(rays, nthreads=_threads())
        return out["t_hit"].numpy(), out["primitive_normals"].numpy()

    def versions(self) -> dict[str, str]:
        return {"open3d": open3d.__version__, "numpy": np.__version__}
