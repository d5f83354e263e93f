"""The mesh reference (:mod:`reference.mesh`) against brute force and analytic shapes."""

from __future__ import annotations

import numpy as np
import pytest

from reference.mesh import MeshSDF
from reference.mesh_cases import mesh_cases, stored_mesh
from reference.primitives import Sphere, Torus

SHAPES = ("torus", "fin", "blob")


def brute_hits(V, F, o, d, t_min=0.0, chunk=64):
    """First hit over all triangles by Möller–Trumbore (Möller & Trumbore, JGT 1997), vectorised."""
    v0, e1, e2 = V[F[:, 0]], V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]
    out = np.full(o.shape[0], np.inf)
    for s in range(0, o.shape[0], chunk):
        oc, dc = o[s : s + chunk], d[s : s + chunk]
        p = np.cross(dc[:, None], e2[None])
        det = np.einsum("fk,rfk->rf", e1, p)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            sv = oc[:, None] - v0[None]
            u = np.einsum("rfk,rfk->rf", sv, p) * inv
            q = np.cross(sv, e1[None])
            v = np.einsum("rk,rfk->rf", dc, q) * inv
            t = np.einsum("fk,rfk->rf", e2, q) * inv
        ok = (det != 0) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > t_min)
        out[s : s + chunk] = np.where(ok, t, np.inf).min(axis=1)
    return out


def brute_distance(V, F, x):
    """Unsigned distance by the closest point on every triangle (trimesh's vectorised
    per-pair closest point, all pairs)."""
    from trimesh.triangles import closest_point

    tri = V[F]
    out = np.empty(x.shape[0])
    for i, p in enumerate(x):
        c = closest_point(tri, np.broadcast_to(p, (F.shape[0], 3)))
        out[i] = np.sqrt(np.min(np.sum((c - p) ** 2, axis=1)))
    return out


def assert_hits_equal(t, tb, what):
    hit = np.isfinite(t)
    assert np.array_equal(hit, np.isfinite(tb)), f"{what}: hit/miss differs on {np.flatnonzero(hit != np.isfinite(tb))}"
    rel = np.abs(t[hit] - tb[hit]) / np.maximum(np.abs(tb[hit]), 1e-300)
    assert rel.max(initial=0.0) <= 1e-12, f"{what}: relative error {rel.max()}"


def rays_at(mesh, n, seed):
    rng = np.random.default_rng(seed)
    c, r = mesh.bounding_sphere()
    o = rng.normal(size=(n, 3))
    o = c + 2.5 * r * o / np.linalg.norm(o, axis=1, keepdims=True)
    tgt = c + rng.uniform(-1, 1, (n, 3)) * r
    d = tgt - o
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


@pytest.mark.parametrize("name", SHAPES)
def test_hits_match_brute_force(name):
    mesh = stored_mesh(name)
    o, d = rays_at(mesh, 200, seed=1)
    t = mesh.first_hit(o, d)
    assert np.isfinite(t).sum() > 50
    assert_hits_equal(t, brute_hits(mesh.vertices, mesh.faces, o, d), name)
    # the hits after a later start (the origins are 2.5 radii from the ball's centre; a start
    # at a hit itself would compare two roundings of the same t against t_min)
    t_min = 2.5 * mesh.bounding_sphere()[1]
    assert_hits_equal(mesh.first_hit(o, d, t_min), brute_hits(mesh.vertices, mesh.faces, o, d, t_min), name)


@pytest.mark.parametrize("name", SHAPES)
def test_hits_along_directions_of_any_length(name):
    """t is the parameter of o + t d, so d of length s gives the unit-direction depths over s.
    Before the culls measured along d/|d|, every ray with |d| ≠ 1 was a miss (0 of 261 hits
    on the fin camera with 3·d)."""
    mesh = stored_mesh(name)
    o, d = rays_at(mesh, 200, seed=2)
    s = np.random.default_rng(3).choice([1e-3, 0.2, 3.0, 1e4], size=(200, 1))
    t = mesh.first_hit(o, d * s)
    assert np.isfinite(t).sum() > 50
    assert_hits_equal(t, brute_hits(mesh.vertices, mesh.faces, o, d * s), name)
    assert_hits_equal(t * s[:, 0], mesh.first_hit(o, d), name)
    t_min = 2.5 * mesh.bounding_sphere()[1]
    assert_hits_equal(mesh.first_hit(o, d * s, t_min / s[:, 0].max()),
                      brute_hits(mesh.vertices, mesh.faces, o, d * s, t_min / s[:, 0].max()), name)


@pytest.mark.parametrize("case", mesh_cases(), ids=lambda c: c.id)
def test_case_hits_match_brute_force(case):
    """Every ray of the mesh cases; the cameras at scale (256², 1024²) on every k-th ray, at most
    4096 (all-triangle brute force costs rays × faces; the trimesh cross-check covers the 256²
    camera in full)."""
    m = case.scene
    idx = np.arange(case.n_rays)[:: max(1, -(-case.n_rays // 4096))]
    o, d = case.origins[idx], case.directions[idx]
    tb = brute_hits(m.vertices, m.faces, o, d, case.t_min)
    tb = np.where(tb <= case.t_max, tb, np.inf)
    t = case.exact_t[idx] if idx.size == case.n_rays else m.first_hit(o, d, case.t_min)
    t = np.where(t <= case.t_max, t, np.inf)
    assert np.isfinite(t).any()
    assert_hits_equal(t, tb, case.id)


@pytest.mark.parametrize("name", SHAPES)
def test_phi_matches_brute_force(name):
    import igl

    mesh = stored_mesh(name)
    rng = np.random.default_rng(2)
    c, r = mesh.bounding_sphere()
    x = c + rng.uniform(-1.1, 1.1, (150, 3)) * r
    # and points near the surface (within 1e-3 of a vertex)
    x = np.concatenate([x, mesh.vertices[rng.integers(0, len(mesh.vertices), 50)] + 1e-3 * rng.normal(size=(50, 3))])
    phi = mesh(x)
    dist = brute_distance(mesh.vertices, mesh.faces, x)
    np.testing.assert_allclose(np.abs(phi), dist, rtol=1e-12, atol=1e-14)
    inside = igl.winding_number(mesh.vertices, mesh.faces, x) > 0.5  # exact, all faces
    assert np.array_equal(phi < 0, inside)


@pytest.mark.parametrize("name", SHAPES)
def test_sign_near_edges_and_vertices_matches_the_exact_winding_number(name):
    """The pseudonormal sign (closest point on an edge or a vertex) against libigl's exact
    winding number, at points 1e-2 … 1e-9 × size from random vertices and edge points, where
    the face-normal test does not decide."""
    import igl

    mesh = stored_mesh(name)
    rng = np.random.default_rng(5)
    V, F = mesh.vertices, mesh.faces
    f = rng.integers(0, len(F), 400)
    s = rng.uniform(0, 1, 400)
    corner = V[F[f, 0]]
    edge = (1 - s)[:, None] * V[F[f, 0]] + s[:, None] * V[F[f, 1]]
    base = np.concatenate([corner, edge])
    scale = mesh.size * 10.0 ** -rng.integers(2, 10, len(base))
    x = base + scale[:, None] * unit_rows(rng.normal(size=(len(base), 3)))
    phi, c, _ = mesh.closest(x)
    keep = np.abs(phi) > 1e-12 * mesh.size  # the sign of a point on the surface is moot
    inside = igl.winding_number(V, F, x[keep]) > 0.5
    assert np.array_equal(phi[keep] < 0, inside), int(np.sum((phi[keep] < 0) != inside))
    assert keep.sum() > 700


def test_sign_at_sharp_edges_where_the_closest_face_normal_is_wrong():
    """A regular tetrahedron (exterior angle between face normals 109.5°): outside points whose
    closest point is on an edge and whose x − c is more than 90° from the face libigl names
    (so ⟨x − c, n_f⟩ < 0 would call them inside).  The edge pseudonormal gets them right."""
    import igl

    V = np.array([[1.0, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]])
    F = np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]])
    mesh = MeshSDF(V, F, name="tetra")
    rng = np.random.default_rng(6)
    # points beyond each edge, in the normal cone of the two faces sharing it
    e = rng.integers(0, 3, 600)
    f = rng.integers(0, 4, 600)
    a, b = V[F[f, e]], V[F[f, (e + 1) % 3]]
    s = rng.uniform(0.1, 0.9, 600)[:, None]
    p = (1 - s) * a + s * b
    n = mesh.face_normals
    n1 = n[f]
    # the other face on edge (a, b)
    other = np.array([[k for k in range(4) if k != fi and {F[fi, ei], F[fi, (ei + 1) % 3]} <= set(F[k])][0]
                      for fi, ei in zip(f, e)])
    n2 = n[other]
    w = rng.uniform(0.02, 0.98, 600)[:, None]
    x = p + 10.0 ** -rng.integers(1, 8, 600)[:, None] * unit_rows(w * n1 + (1 - w) * n2)
    phi, c, face = mesh.closest(x)
    assert np.all(phi > 0)
    assert np.array_equal(phi < 0, igl.winding_number(V, F, x) > 0.5)
    wrong_by_face = np.einsum("ij,ij->i", x - c, mesh.face_normals[face]) < 0
    assert wrong_by_face.sum() > 50  # the face-normal test alone would fail here


def test_non_finite_points_skip_the_tree():
    mesh = stored_mesh("fin")
    x = np.array([[0.0, 0, 5], [np.inf, 0, 0], [np.nan, 0, 0], [0.1, 0.1, 0.1], [-np.inf, np.nan, 1]])
    phi, c, face = mesh.closest(x)
    assert phi[0] > 0 and phi[1] == np.inf and np.isnan(phi[2]) and np.isnan(phi[4])
    assert np.all(face[1:3] == -1) and np.isnan(c[1]).all() and face[3] >= 0
    np.testing.assert_array_equal(phi[[0, 3]], mesh.closest(x[[0, 3]])[0])


def unit_rows(v):
    return v / np.linalg.norm(v, axis=1, keepdims=True)


@pytest.mark.parametrize("name", SHAPES)
def test_gradient_normals_closest_points(name):
    mesh = stored_mesh(name)
    rng = np.random.default_rng(3)
    c, r = mesh.bounding_sphere()
    x = c + rng.uniform(-1.1, 1.1, (300, 3)) * r
    phi, g, dth = mesh.jet(x)
    assert dth.shape == (300, 0)
    np.testing.assert_allclose(np.linalg.norm(g, axis=1), 1.0, atol=1e-12)
    cp = mesh.closest_point_exact(x)
    np.testing.assert_allclose(x - phi[:, None] * g, cp, atol=1e-12)
    np.testing.assert_allclose(np.abs(mesh(cp)), 0.0, atol=1e-12)
    # finite differences of φ agree with ∇φ away from the medial axis (step ≪ |φ|)
    h = 1e-6
    fd = np.stack([(mesh(x + h * e) - mesh(x - h * e)) / (2 * h) for e in np.eye(3)], axis=1)
    good = np.abs(phi) > 1e-2
    assert np.quantile(np.linalg.norm(fd - g, axis=1)[good], 0.9) < 1e-6
    # at hits the normal is the hit face's outward normal
    o, d = rays_at(mesh, 100, seed=4)
    r_idx, t, f = mesh.ray_hits(o, d, 0.0)
    first = np.full(len(o), np.inf)
    np.minimum.at(first, r_idx, t)
    sel = np.isfinite(first[r_idx]) & (t == first[r_idx])
    xh = o[r_idx[sel]] + t[sel, None] * d[r_idx[sel]]
    np.testing.assert_allclose(mesh.normal_exact(xh), mesh.face_normals[f[sel]], atol=1e-9)


@pytest.mark.parametrize("name", SHAPES)
def test_intervals_consistent_with_first_hit(name):
    mesh = stored_mesh(name)
    o, d = rays_at(mesh, 150, seed=5)
    iv = mesh.ray_intervals(o, d)
    t = mesh.first_hit(o, d)
    for i, b in enumerate(iv):
        assert b.size % 2 == 0 and np.all(np.diff(b) > 0)
        first = b[b > 0].min(initial=np.inf)
        assert first == t[i] or (np.isinf(first) and np.isfinite(t[i]))  # touches bound no interval
        if b.size:
            mid = 0.5 * (b[0::2] + b[1::2])
            assert np.all(mesh(o[i] + mid[:, None] * d[i]) < 0)


def _icosphere(k):
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=k)
    return MeshSDF(m.vertices, m.faces, name=f"icosphere{k}")


def test_icosphere_converges_to_sphere_at_second_order():
    """Vertices on the unit sphere, edge length h ∝ 2^-k: the chordal error is O(h²), so each
    subdivision divides the φ and hit errors by about 4."""
    rng = np.random.default_rng(6)
    x = rng.normal(size=(400, 3))
    x *= rng.uniform(0.3, 1.5, (400, 1)) / np.linalg.norm(x, axis=1, keepdims=True)
    o, d = rays_at(_icosphere(1), 300, seed=7)
    sph = Sphere()
    t_exact = sph.first_hit(o, d)
    hit = np.isfinite(t_exact) & (np.abs(np.einsum("ij,ij->i", o + t_exact[:, None] * d, d)) > 0.2)  # not grazing
    err_phi, err_t = [], []
    for k in (2, 3, 4, 5):
        m = _icosphere(k)
        err_phi.append(np.max(np.abs(m(x) - sph(x))))
        err_t.append(np.max(np.abs(m.first_hit(o, d)[hit] - t_exact[hit])))
    for errs in (err_phi, err_t):
        ratios = np.array(errs[:-1]) / np.array(errs[1:])
        assert np.all((ratios > 3.0) & (ratios < 5.0)), (errs, ratios)
    assert err_phi[-1] < 5e-4


def test_torus_mesh_near_analytic_torus():
    """Vertices on the analytic torus: |φ_mesh − φ_torus| is at most the chordal error of the
    64 × 32 sections, ≈ R(1 − cos(π/64)) + r(1 − cos(π/32)) plus the chord of the diagonal."""
    mesh, tor = stored_mesh("torus"), Torus(1.0, 0.25)
    rng = np.random.default_rng(8)
    x = rng.uniform(-1.4, 1.4, (500, 3)) * [1, 1, 0.3]
    bound = 1.25 * (1 - np.cos(np.pi / 64)) + 0.25 * (1 - np.cos(np.pi / 32))
    err = np.abs(mesh(x) - tor(x))
    assert err.max() <= 2 * bound
    assert err.max() > 0.1 * bound  # the mesh is not the torus


def test_torch_and_jax_agree_with_numpy():
    torch = pytest.importorskip("torch")
    jax = pytest.importorskip("jax")
    jax.config.update("jax_enable_x64", True)
    import array_api_compat.torch as xpt
    import jax.numpy as jnp

    mesh = stored_mesh("blob")
    rng = np.random.default_rng(9)
    x = rng.uniform(-1.2, 1.2, (64, 3))
    dx = rng.normal(size=(64, 3))
    phi, g, _ = mesh.jet(x)

    xt = torch.tensor(x, requires_grad=True)
    pt = mesh.value(xt, xpt)
    (gt,) = torch.autograd.grad(pt.sum(), xt)
    np.testing.assert_allclose(pt.detach().numpy(), phi, rtol=0, atol=1e-12)
    np.testing.assert_allclose(gt.numpy(), g, rtol=0, atol=1e-12)
    _, tt = torch.func.jvp(lambda y: mesh.value(y, xpt), (torch.tensor(x),), (torch.tensor(dx),))
    np.testing.assert_allclose(tt.numpy(), np.sum(g * dx, axis=1), rtol=0, atol=1e-12)
    p32 = mesh.value(torch.tensor(x, dtype=torch.float32), xpt)
    assert p32.dtype == torch.float32
    with pytest.raises(RuntimeError, match="differentiable once"):
        (g2,) = torch.autograd.grad(mesh.value(xt, xpt).sum(), xt, create_graph=True)

    f = lambda y: mesh.value(y, jnp)
    xj = jnp.asarray(x)
    np.testing.assert_allclose(np.asarray(jax.jit(f)(xj)), phi, rtol=0, atol=1e-12)
    gj = jax.jit(jax.grad(lambda y: f(y).sum()))(xj)
    np.testing.assert_allclose(np.asarray(gj), g, rtol=0, atol=1e-12)
    _, tj = jax.jvp(f, (xj,), (jnp.asarray(dx),))
    np.testing.assert_allclose(np.asarray(tj), np.sum(g * dx, axis=1), rtol=0, atol=1e-12)
    with pytest.raises(Exception, match="(?i)jvp"):
        jax.hessian(lambda y: f(y[None])[0])(xj[0])


def test_bad_input_raises():
    import trimesh

    m = trimesh.creation.icosphere(1)
    V, F = np.asarray(m.vertices), np.asarray(m.faces)
    with pytest.raises(ValueError, match="watertight"):
        MeshSDF(V, F[1:])
    flipped = F.copy()
    flipped[0] = flipped[0, ::-1]
    with pytest.raises(ValueError, match="consistently oriented"):
        MeshSDF(V, flipped)
    with pytest.raises(ValueError, match="inward"):
        MeshSDF(V, F[:, ::-1])
    with pytest.raises(ValueError, match="vertices"):
        MeshSDF(V[:, :2], F)
    with pytest.raises(ValueError, match="vertices"):
        MeshSDF(np.where(np.arange(len(V))[:, None] == 0, np.nan, V), F)
    with pytest.raises(ValueError, match="faces"):
        MeshSDF(V, F.astype(float))
    with pytest.raises(ValueError, match="faces index"):
        MeshSDF(V, F + len(V))
    with pytest.raises(ValueError, match="not found"):
        MeshSDF.load("no-such-mesh")
    with pytest.raises(ValueError, match=r"\(n, 3\)"):
        stored_mesh("fin").first_hit(np.zeros(3), np.ones(3))


def test_spec_identifies_the_mesh():
    a, b = stored_mesh("torus"), MeshSDF.load("torus")
    assert a.content_hash() == b.content_hash() != stored_mesh("blob").content_hash()
    assert a.param_vector().size == 0 and a.with_params(np.zeros(0)) is a
    assert a.info.exact_sdf and a.info.exact_hits and not a.info.exact_curvature


def test_stored_files_are_reproducible():
    from reference import make_meshes

    for name, make in make_meshes.SHAPES.items():
        V, F = make()
        m = stored_mesh(name)
        np.testing.assert_array_equal(V, m.vertices)
        np.testing.assert_array_equal(F, m.faces)


def test_a_deep_copy_of_a_queried_mesh_evaluates_the_same():
    """A plug-in backend gets a deep copy of the scene (bench.run.configuration.own_copy); a mesh
    that had answered a query held libigl's AABB tree, which cannot be copied ("cannot pickle
    'AABB' object": every plug-in row on a mesh case failed).  The copy leaves derived caches out
    and builds them again."""
    import copy

    from reference.cases import get_case

    case = get_case("mesh.torus.camera.16x16")
    x = case.origins[:64] + 2.0 * case.directions[:64]
    phi = np.asarray(case.scene.value(x))
    twin = copy.deepcopy(case.scene)
    assert np.array_equal(np.asarray(twin.value(x)), phi)
    assert repr(twin.spec()) == repr(case.scene.spec())
