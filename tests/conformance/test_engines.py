"""Engines: raycast on triangle meshes (impls/engine.py)."""

from __future__ import annotations

import numpy as np
import pytest

from impls import METHODS, Declined, Status
from reference.rays import normalize, pinhole
from tests.conformance.common import SCENES, camera, plant_bad_rays

# -- engines: raycast on triangle meshes (impls/engine.py) --------------------------------------------

def _mesh_scene():
    pytest.importorskip("trimesh")
    pytest.importorskip("igl")
    from reference.mesh_cases import stored_mesh

    return stored_mesh("torus")


def _engine(backend):
    """``backend`` if it offers ``raycast`` (an engine), else a skip: the built-in backends leave it
    out of methods() (MethodSpec.libs = ()), which a run records as 'does not implement'."""
    if "raycast" not in backend.methods():
        pytest.skip(f"{backend.id} does not offer raycast (MethodSpec.libs = (): an engine's own query)")
    return backend


def _raycast(backend, scene, o, d, **kw):
    prep = backend.prepare("raycast", scene, o, d, dtype="float32", **kw)
    out = prep.run()
    backend.synchronize(out)
    return prep.result(out)


def _mesh_camera(n=24):
    return pinhole(eye=(0.0, -2.5, 1.8), look_at=(0.0, 0.0, 0.0), fov_deg=45.0, width=n, height=n)


def test_raycast_is_offered_by_no_array_library_backend(any_backend):
    if "raycast" in any_backend.methods():
        # an engine computes in float32 (warp also runs the root finders, in float64)
        assert set(METHODS["raycast"].dtypes) <= set(any_backend.capabilities.dtypes)
        return
    assert METHODS["raycast"].libs == () and METHODS["raycast"].family == "root" and not METHODS["raycast"].knobs


def test_raycast_depth_and_normal_against_exact(any_backend):
    """A camera at the torus mesh: every ray's hit or miss as the exact float64 hit says, each depth
    within float32's √ε · max(1, T) (the tolerance bench judges float32 rows by), the normal the
    hit face's (engines' float32 normals, to float32 rounding)."""
    from bench.studies.stability import depth_tolerance

    b, scene = _engine(any_backend), _mesh_scene()
    o, d = _mesh_camera()
    exact = scene.first_hit(o, d, 0.0)
    hit = np.isfinite(exact)
    assert hit.any() and (~hit).any()
    r = _raycast(b, scene, o, d)
    assert np.all(r.status[hit] == Status.CONVERGED) and np.all(r.status[~hit] == Status.MISS), r.status_counts()
    assert np.all(np.isinf(r.t[~hit])) and np.all(np.isnan(r.outputs["normal"][~hit]))
    err = np.abs(r.t[hit] - exact[hit])
    assert err.max() <= depth_tolerance("float32", exact[hit].max()), err.max()
    # the depth is the engine's float32 number, widened exactly
    np.testing.assert_array_equal(r.t[hit], r.t[hit].astype(np.float32).astype(np.float64))
    x = o[hit] + exact[hit, None] * d[hit]
    cos = np.einsum("ij,ij->i", r.outputs["normal"][hit], scene.normal_exact(x))
    assert np.all(cos >= 1 - 1e-5), cos.min()
    assert np.all(r.evals == 0) and np.all(r.iterations == 0)


def test_raycast_batched_equals_per_ray(any_backend):
    b, scene = _engine(any_backend), _mesh_scene()
    o, d = _mesh_camera(6)
    r = _raycast(b, scene, o, d)
    for i in range(0, len(o), 5):
        ri = _raycast(b, scene, o[i:i + 1], d[i:i + 1])
        assert ri.status[0] == r.status[i]
        np.testing.assert_array_equal(ri.t[:1], r.t[i:i + 1])


def test_raycast_range_and_inside_origins(any_backend):
    """t_max before the first hit: MISS; t_min past the entry: the exit (the next crossing); an
    origin inside the solid: its exit."""
    b, scene = _engine(any_backend), _mesh_scene()
    o, d = _mesh_camera(8)
    exact = scene.first_hit(o, d, 0.0)
    hit = np.isfinite(exact)
    cut = _raycast(b, scene, o, d, t_max=float(exact[hit].min()) * 0.5)
    assert np.all(cut.status == Status.MISS)
    t_min = float(exact[hit].max()) + 1e-3
    later = _raycast(b, scene, o, d, t_min=t_min)
    exact_later = scene.first_hit(o, d, t_min)
    lh = np.isfinite(exact_later)
    assert np.all((later.status == Status.CONVERGED) == lh)
    assert np.abs(later.t[lh] - exact_later[lh]).max() <= 1e-4
    inside_o = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.05]])  # on the tube's core circle
    inside_d = normalize(np.array([[0.0, 0.3, 1.0], [1.0, 0.0, 0.0]]))
    r = _raycast(b, scene, inside_o, inside_d)
    ex = scene.first_hit(inside_o, inside_d, 0.0)
    assert np.all(r.status == Status.CONVERGED) and np.abs(r.t - ex).max() <= 1e-5


def test_raycast_starts_far_along_the_ray_in_float64(any_backend):
    """Rays that start 1e6 back and skip the way with t_min = 1e6: the start o + t_min·d is computed
    in float64, then rounded, and t_min added back in float64, on every engine.  Warp's and
    Mitsuba's query (through ArrayBackend.prepare) rounded the rays first: a start off by float32's
    spacing at 1e6 (0.06), 1 false hit, 2 false misses and a depth error of 0.23 on a 16² camera at
    the unit icosphere (Embree and Open3D: 0, 0, 1.2e-6)."""
    from bench.studies.stability import depth_tolerance

    b, scene = _engine(any_backend), _mesh_scene()
    o, d = _mesh_camera(16)
    o = o - 1e6 * d
    exact = scene.first_hit(o, d, 1e6)
    hit = np.isfinite(exact) & (exact <= 1e6 + 10)
    assert hit.any() and (~hit).any()
    r = _raycast(b, scene, o, d, t_min=1e6, t_max=1e6 + 10)
    assert np.all((r.status == Status.CONVERGED) == hit), r.status_counts()
    err = np.abs(r.t[hit] - exact[hit])
    assert err.max() <= depth_tolerance("float32", 10.0), err.max()  # (a depth 10 along the start's ray)


@pytest.mark.filterwarnings("ignore:invalid value:RuntimeWarning")
def test_raycast_flags_bad_rays(any_backend):
    b, scene = _engine(any_backend), _mesh_scene()
    o, d, bad = plant_bad_rays(*_mesh_camera(3))
    r = _raycast(b, scene, o, d)
    assert np.all(r.status[bad] == Status.BAD_INPUT) and np.all(np.isnan(r.t[bad]))
    assert np.all(np.isnan(r.outputs["normal"][bad]))
    good = _raycast(b, scene, o[~bad], d[~bad])
    np.testing.assert_array_equal(r.status[~bad], good.status)
    np.testing.assert_array_equal(r.t[~bad], good.t)


def test_raycast_declines_other_scenes_and_refuses_bad_arguments(any_backend):
    from impls.protocol import declined_reason

    b, scene = _engine(any_backend), _mesh_scene()
    o, d = camera(2)
    for other in SCENES.values():
        assert "triangle meshes" in declined_reason(b, "raycast", other)  # (mitsuba also takes grid SDFs)
        with pytest.raises(Declined, match="triangle meshes"):
            b.prepare("raycast", other, o, d, dtype="float32")
    assert declined_reason(b, "raycast", scene) is None
    with pytest.raises(ValueError, match="dtype='float32'"):
        b.prepare("raycast", scene, o, d, dtype="float64")
    with pytest.raises(ValueError, match="unknown knob"):
        b.prepare("raycast", scene, o, d, dtype="float32", xtol=1e-6)
    with pytest.raises(ValueError, match="t_hit"):
        b.prepare("raycast", scene, o, d, dtype="float32", t_hit=np.ones(len(o)))
    with pytest.raises(ValueError, match="directions"):
        b.prepare("raycast", scene, o, 2 * d, dtype="float32")
    with pytest.raises(NotImplementedError, match="raycast" if "hybrid_secant" not in b.methods() else "MeshSDF"):
        b.prepare("hybrid_secant", scene, o, d, dtype="float32")  # (warp offers it, and declines meshes)
    prep = b.prepare("raycast", scene, o, d, dtype="float32")
    again = b.prepare("raycast", scene, o, d, dtype="float32")
    assert prep.compile_cache in ("compiled", "reused") and again.compile_cache == "reused"
    assert set(b.versions()) and all(isinstance(v, str) for v in b.versions().values())
