"""Cases on the stored neural SDF (:mod:`reference.neural`), for the catalog to register.

Ids ``neural.blob.<family>``; the scene is :class:`reference.neural.NeuralSDF` (the softplus MLP
fitted to the ``blob`` mesh) with its spectral Lipschitz bound, or, where the id ends in
``.Llocal``, the tighter bound certified on its box (:mod:`reference.neural`).  Exact first hits come from the certified
numerical reference (:func:`reference.numerical.first_hit_numeric`).  Each case is built only
when a run selects it (:func:`reference.cases.register_each`); the network is loaded once per
process (:func:`stored_network`).
"""

from __future__ import annotations

import functools

import numpy as np

from . import rays as _rays
from .cases import LARGE_SIZES, Case, DeclaredLipschitz, _cam, large_tags, make_case, register_each
from .neural import NeuralSDF

#: the factor of the measured slope that the ``understated`` case declares as its Lipschitz bound
UNDERSTATED_FACTOR = 0.5


@functools.cache
def stored_network(lipschitz: str = "spectral") -> NeuralSDF:
    """The stored network with Lipschitz mode ``lipschitz``, one instance per mode and process."""
    return NeuralSDF(lipschitz=lipschitz)


def surface_points(net: NeuralSDF, n: int, seed: int) -> np.ndarray:
    """``n`` points on the network's zero set: the first crossing of rays from the centre of its
    surface box in seeded uniform directions (certified numerical reference, local bound)."""
    from .numerical import first_hit_numeric

    lo, hi = net.surface_box
    c = 0.5 * (lo + hi)
    u = _rays.random_directions(n, seed)
    o = np.broadcast_to(c, u.shape).copy()
    t, _ = first_hit_numeric(net.with_lipschitz("local"), o, u, 0.0, float(np.linalg.norm(hi - lo)), n_samples=128)
    if not np.all(np.isfinite(t)):
        raise AssertionError("a ray from the centre of the neural blob found no surface")
    return o + t[:, None] * u


def grazing_rays(net: NeuralSDF, n: int, offset: float, seed: int, back: float = 2.5):
    """Rays tangent to the surface at points p of it, along the direction of largest normal
    curvature κ₁ > 0 (φ grows quadratically along them, ½κ₁|∇φ|s²), moved by ±``offset`` along
    the normal n: even rays at p + offset·n (just outside: a near miss there), odd rays at
    p − offset·n (just inside: two crossings ~√(2·offset/κ₁) either side of p).  Origins are
    ``back`` before p along the ray (outside the surface box).  Points with κ₁ < 0.3 (too flat for
    the offset to decide the ray) are skipped."""
    from .curvature import tangent_basis

    p = surface_points(net, 2 * n, seed)
    _, g, H = net.gradient_hessian(p)
    gn = np.linalg.norm(g, axis=1)
    nrm = g / gn[:, None]
    t1, t2 = tangent_basis(nrm)
    b11 = np.einsum("ni,nij,nj->n", t1, H, t1) / gn
    b22 = np.einsum("ni,nij,nj->n", t2, H, t2) / gn
    b12 = np.einsum("ni,nij,nj->n", t1, H, t2) / gn
    ang = 0.5 * np.arctan2(2 * b12, b11 - b22)  # the eigenvector of the larger eigenvalue
    d = np.cos(ang)[:, None] * t1 + np.sin(ang)[:, None] * t2
    k1 = 0.5 * (b11 + b22) + np.hypot(0.5 * (b11 - b22), b12)
    keep = np.flatnonzero(k1 >= 0.3)[:n]
    if keep.size < n:
        raise AssertionError(f"only {keep.size} of {2 * n} surface points have κ₁ ≥ 0.3")
    p, nrm, d = p[keep], nrm[keep], _rays.normalize(d[keep])
    s = np.where(np.arange(n) % 2 == 0, 1.0, -1.0)
    x = p + (s * offset)[:, None] * nrm
    return x - back * d, d


def _case(case_id, scene, o, d, tags, description) -> Case:
    return make_case(case_id, scene, o, d, tags=tags, description=description, t_max=6.0)


#: the structural tags of a neural case's scene (:func:`reference.cases.case_tags` of a :class:`NeuralSDF`)
NEURAL_SCENE_TAGS = ("neural", "lipschitz", "numerical")


def _neural_specs() -> dict:
    """id → (build() → (scene, origins, directions, description), the case's own tags) of every
    neural case, in catalog order."""
    def spectral_cam():
        spectral = stored_network("spectral")
        return (spectral, *_cam(16, fov=50.0),
                f"the stored 3→64→64→1 softplus (β = 100) network fitted to the blob mesh, 16×16 camera; spectral "
                f"Lipschitz bound ∏‖Wₖ‖₂ = {spectral.spectral_bound:.3g} (certified everywhere)")

    def local_cam():
        local = stored_network("local")
        return (local, *_cam(16, fov=50.0),
                f"the same network and rays with the local bound {local.local_bound:.3g}, certified on its surface box "
                f"by interval bounds (largest measured slope {local.measured_slope:.4g})")

    def large_cam(n):
        local = stored_network("local")
        return (local, *_cam(n, fov=50.0),
                f"the network with its local bound {local.local_bound:.3g}, {n}×{n} camera (the 16×16 view "
                "at scale); hits from the certified numerical reference (its cost grows with the rays: "
                "minutes at 256², hours at 1024²)")

    def grazing(k, n):
        local = stored_network("local")
        return (local, *grazing_rays(local, n, 10.0**-k, seed=120 + k),
                f"rays tangent to the network's surface along its direction of largest curvature, 1e-{k} "
                "outside (even rays) or inside (odd rays) it; local bound")

    def understated():
        lie = DeclaredLipschitz(stored_network("local"), UNDERSTATED_FACTOR * stored_network("local").measured_slope)
        o, d = _rays.in_ball(256, 0.5, seed=130)
        return (lie, o, d,
                f"the network declared with L = {UNDERSTATED_FACTOR} × its largest measured slope "
                f"({lie.declared:.3g}, below the true slope of ≈ 1 almost everywhere); origins inside "
                "(|o| ≤ 0.5), random directions: a step of |φ|/L crosses the surface, which the check must flag; "
                "exact hits from the network's own certified (local) bound")

    specs = {"neural.blob.camera.16x16": (spectral_cam, ("camera", "quick")),
             "neural.blob.camera.16x16.Llocal": (local_cam, ("camera",))}
    # grazing rays with the local bound: certifying a near miss at distance δ costs ~L/√δ
    # evaluations per ray (the reference halves intervals until |φ(a)| + |φ(b)| > L(b − a)),
    # 5× fewer than with the spectral bound
    for k, n in ((3, 128), (6, 64)):
        specs[f"neural.blob.grazing.1e-{k}.Llocal"] = (lambda k=k, n=n: grazing(k, n), ("grazing",))
    specs["neural.blob.understated"] = (understated, ("understated", "inside"))
    for n in LARGE_SIZES:
        specs[f"neural.blob.camera.{n}x{n}.Llocal"] = (lambda n=n: large_cam(n), large_tags(n))
    return specs


_NEURAL_SPECS = _neural_specs()
#: the ids :func:`neural_case` builds, registered in the catalog without building them (tags
#: declared: a suite chosen by tag loads no network it does not run)
NEURAL_CASE_IDS = tuple(_NEURAL_SPECS)


def neural_case(case_id: str) -> Case:
    """The neural case ``case_id`` (one of :data:`NEURAL_CASE_IDS`)."""
    build, tags = _NEURAL_SPECS[case_id]
    scene, o, d, description = build()
    return _case(case_id, scene, o, d, tags, description)


def neural_cases() -> list[Case]:
    """Every neural case of the catalog (:data:`NEURAL_CASE_IDS`)."""
    from .cases import get_case

    return [get_case(cid) for cid in NEURAL_CASE_IDS]


register_each({cid: NEURAL_SCENE_TAGS + tags for cid, (_, tags) in _NEURAL_SPECS.items()}, neural_case)
