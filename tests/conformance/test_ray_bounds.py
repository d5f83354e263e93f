"""Knob ``bounds``: clipping rays to the scene's ray bounds changes no answer and skips the rest
(in a file of its own: its grazing rays take tens of thousands of sphere-tracing steps, and
``--dist loadfile`` runs each file on one worker)."""

from __future__ import annotations

import numpy as np
import pytest

from impls import Status
from impls.core.methods_root import checks_inside
from reference.rays import normalize
from tests.conformance.common import ROOT_METHODS, SCENES, TIGHT, camera, depth_resolved, run


def silhouette_rays(ball, n=64, delta_min=1e-12, hit_delta_min=None):
    """Rays from distance 3 that pass the ball's centre at impact parameters r(1 − δ), δ from
    ``hit_delta_min`` (default ``delta_min``) to 1e-2, and r(1 + δ), δ from ``delta_min`` to 1e-2
    (the rays the clipping's padding must not turn from hits into misses or back), plus rays
    that miss the ball by a wide margin."""
    c, r = ball
    rng = np.random.default_rng(3)
    inner = np.geomspace(delta_min if hit_delta_min is None else hit_delta_min, 1e-2, n // 2)
    b = r * np.concatenate([1 - inner, 1 + np.geomspace(delta_min, 1e-2, n // 2), [1.5, 3.0]])
    u = normalize(rng.normal(size=(b.size, 3)))
    d = normalize(np.cross(u, rng.normal(size=(b.size, 3))))  # ⟂ u
    return c + b[:, None] * u - 3.0 * d, d


@pytest.mark.slow  # compiles many kernels or sweeps a whole catalog
@pytest.mark.parametrize("method", ROOT_METHODS)
@pytest.mark.parametrize("scene_name", ["sphere", "union"])
def test_ray_bounds_clip_keeps_every_answer_and_skips_the_rest(any_backend, method, scene_name):
    """Knob ``bounds``: clipping rays to the scene's ray bounds (here the default, the chord of
    the bounding sphere; the reference scenes' tighter bounds are covered by every conformance
    case, which runs with the clip on) changes no answer (status, depth), makes rays that miss
    the ball a MISS after the start evaluation and no iteration, and costs fewer evaluations in
    all.  Certified methods also get rays grazing the ball (the sphere's own silhouette); the
    marchers, which may miss a chord shorter than their step wherever their samples fall, get
    the camera's rays only."""
    scene = SCENES[scene_name]
    ball = scene.bounding_sphere()
    o, d = camera(8)
    n_camera = len(o)
    if method in ("sphere_trace", "hybrid_secant", "hybrid_chandrupatla"):
        # plain sphere tracing certifies a miss that passes δ·r from the surface in ~1/√δ steps
        # (never, when δ·r < tol; 14k at δ = 1e-7), and converges on a hit at δ in
        # ~ln(1/tol)/√(2δ) steps (93k at δ = 1e-8), every backend's loop running as long as its
        # slowest ray: its misses get δ ≥ 5e-7, which still puts rays on both sides of the padding
        # (1e-6 of the radius, the band the clip must neither cut a hit from nor add a miss to:
        # reference/raybounds.py), its hits δ ≥ 1e-5 (3.7k steps), still too grazing to certify
        # (`graze` below).  (Misses from 1e-7 and hits from 1e-7 took 26–78 s a backend on a 2-core
        # machine, 3–5 s with these.)  The hybrids' rays inside the band, down to δ = 1e-12, are
        # clipped by the same code (impls/core/rootfind.py:clip_to_bounds).
        sphere = method == "sphere_trace"
        o2, d2 = silhouette_rays(ball, delta_min=5e-7 if sphere else 1e-12, hit_delta_min=1e-5 if sphere else None)
        o, d = np.concatenate([o, o2]), np.concatenate([d, d2])
    exact = scene.first_hit(o, d, 0.0)
    hit = np.isfinite(exact)
    knobs = dict(TIGHT[method], max_steps=200000) if method == "sphere_trace" else TIGHT[method]
    on = run(any_backend, method, scene, o, d, bounds=1, **knobs)
    off = run(any_backend, method, scene, o, d, bounds=0, **knobs)
    outside = np.linalg.norm(np.cross(ball[0] - o, d), axis=1) > ball[1] * (1 + 1e-3)
    assert outside.any() and hit.any()
    # MISS before any evaluation: no evaluation, no iteration; every other ray evaluates
    assert np.all(on.status[outside] == Status.MISS)
    assert np.all(on.evals[outside] == 0) and np.all(on.iterations[outside] == 0)
    assert np.all(on.evals[hit] >= 1) and np.all(off.evals >= 1)
    # the hybrids certify a crossing approached at a slope of at least PASSING_SLOPE (in units of L;
    # a sphere's chord c at radius r is crossed at slope c/2r): below it the ray passes nearly tangent
    # on forced steps that stand uncertified, and its hit may be UNCERTIFIED (2× margin here)
    from impls.core.rootfind import PASSING_SLOPE

    spheres = scene.children or (scene,)
    slope = np.max([[(b[1] - b[0]) / (2 * s.radius) if b.size else 0.0 for b in s.ray_intervals(o, d)]
                    for s in spheres], axis=0)
    # and, as sphere tracing's, a hit crossed so obliquely that φ stays within its rounding over a
    # stretch wider than the tolerance cannot be bracketed to it: it may be UNCERTIFIED (depth_resolved)
    sure = hit
    if method in ("hybrid_secant", "hybrid_chandrupatla"):
        sure = hit & (slope >= 2 * PASSING_SLOPE) & depth_resolved(method, scene, o, d, exact, knobs)
        assert sure[:n_camera].sum() >= 0.8 * hit[:n_camera].sum()
    if method == "sphere_trace":
        sure = depth_resolved(method, scene, o, d, exact, knobs)
        assert sure[:n_camera].sum() >= 0.8 * hit[:n_camera].sum()
    # a certified MISS needs certified steps all along: a silhouette ray passing closer to the surface
    # than the forced step's reach or the probe's is an uncertified miss (UNCERTIFIED, t = inf)
    near_miss = ~hit & (np.arange(len(o)) >= n_camera)
    if method.startswith("march_") and checks_inside(scene):
        # a bound taken on trust (this module's own Field subclasses) covers no march step
        # (ConstantStep.cover): a march's MISS is then certified by the ray bounds alone, before any
        # step (the rays outside the ball, with the clip on, as asserted above), and its crossing
        # only within a step of its start (UNCERTIFIED further on, with its depth)
        near_miss = ~hit
        sure = np.zeros_like(hit)
    for r in (on, off):
        assert np.all(r.status[sure] == Status.CONVERGED) and np.all(r.status[~hit & ~near_miss] == Status.MISS), \
            r.status_counts()
        assert np.all(np.isin(r.status[near_miss], (Status.MISS, Status.UNCERTIFIED))), r.status_counts()
        assert np.all(np.isinf(r.t[~hit]))
        np.testing.assert_allclose(r.t[sure], exact[sure], rtol=0, atol=1e-9)
        graze = hit & ~sure
        assert np.all(np.isin(r.status[graze], (Status.CONVERGED, Status.UNCERTIFIED))), r.status_counts()
        conv = graze & (r.status == Status.CONVERGED)
        np.testing.assert_allclose(r.t[conv], exact[conv], rtol=0, atol=1e-9)
        if method.startswith("march_") and checks_inside(scene):
            # (the march found these crossings; it only cannot prove them the first: their depths)
            np.testing.assert_allclose(r.t[hit], exact[hit], rtol=0, atol=1e-9)
    assert on.evals.sum() < off.evals.sum()

