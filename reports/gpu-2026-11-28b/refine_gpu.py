"""GPU check of sphere tracing's bracket refinement and of the certificate withdrawal on a refuted
bound (``python reports/gpu-2026-11-28b/refine_gpu.py BACKENDS [SIDE]``; BACKENDS e.g.
``torch:cuda,jax:gpu``, or ``numpy,torch:cpu,jax:cpu`` for the same rows on a CPU).

Scenes not in the case catalog, each with its exact answers from ``reference``:

* ``far32``: seeded thin walls (shells and plates 2e-4 … 2e-2 thick, a torus) moved 1e4 along x,
  float32, SIDE² rays: a CONVERGED depth must lie within δ = 4·rounding of the first crossing
  (docs/methods.md), and no MISS may be certified on a ray that hits;
* ``walls64``: the same walls at the origin in float64: the first-crossing guarantee ray by ray
  (CONVERGED within 1e-6 of a crossing, only pairs narrower than the allowance passed before it);
* ``liar``: the walls at 4× their distance bound declared with L = 1 (a ``DeclaredLipschitz``):
  every ray must end without a certificate (no CONVERGED, no MISS: the bound is refuted);
* ``sphere32``: the unit sphere's 64² camera in float32 at the default tol, whose oblique hits go
  through the refinement stage: the statuses must be numpy's (jax runs the fused ``step_masked``).

Prints one line per (scene, backend, method): status counts, wrong certified answers, wall time of
the second run (the first holds compilation)."""

from __future__ import annotations

import sys
import time

import numpy as np

from impls import registry
from impls.core.methods_root import rounding_scale
from impls.protocol import Status
from reference import get_case, rays
from reference.cases import DeclaredLipschitz
from reference.csg import Difference, Union
from reference.implicits import Scaled
from reference.primitives import Box, Sphere, Torus
from reference.transform import Transform


def thin_walls(seed: int, side: int):
    """The thin walls of tests/test_certified_at_scale.py (same seeds, same scene), side² rays.
    A copy, not an import: that module imports the test suite's conftest (bench's environment,
    filelock, hypothesis), which a lent GPU image need not have; this script needs only isobench."""
    rng = np.random.default_rng(seed)
    parts = []
    for _ in range(3):
        c = tuple(rng.uniform(-0.4, 0.4, 3))
        r = rng.uniform(0.3, 0.6)
        w = 10.0 ** rng.uniform(-3.7, -1.7)
        parts.append(Difference(Sphere(center=c, radius=r + w), Sphere(center=c, radius=r)))
    for _ in range(2):
        w = 10.0 ** rng.uniform(-3.7, -1.7)
        plate = Box((rng.uniform(0.3, 0.8), rng.uniform(0.3, 0.8), w))
        parts.append(Transform.from_rotvec(plate, tuple(rng.normal(size=3)), tuple(rng.uniform(-0.3, 0.3, 3))))
    parts.append(Torus(rng.uniform(0.5, 0.8), rng.uniform(0.01, 0.05)))
    o, d = rays.pinhole(eye=tuple(rng.normal(size=3) * 0.3 + np.array([0.0, 0.0, 3.0])), look_at=(0, 0, 0),
                        fov_deg=45, width=side, height=side)
    return Union(*parts), o, d


def guarantee(intervals, res, allow: float, t_max: float) -> int:
    """Rays breaking the first-crossing guarantee (tests/test_certified_at_scale.py:check_guarantee)."""
    bad = 0
    for i, iv in enumerate(intervals):
        st, t = int(res.status[i]), float(res.t[i])
        c = np.sort(np.asarray(iv, float).ravel())
        c = c[(c > 0) & (c <= t_max)]
        if st == Status.CONVERGED:
            near = np.abs(c - t) <= 1e-6 * max(1.0, abs(t))
            passed = c[:int(np.argmax(near))] if near.any() else c
            bad += (not near.any()) or passed.size % 2 == 1 or bool(np.any(passed[1::2] - passed[0::2] >= allow))
        elif st == Status.MISS and c.size:
            bad += 1
    return bad


def solve(backend, method, scene, o, d, dtype, t_max):
    p = backend.prepare(method, scene, o, d, dtype=dtype, t_min=0.0, t_max=t_max)
    out = p.run()
    backend.synchronize(out)
    t0 = time.perf_counter()
    out = p.run()
    backend.synchronize(out)
    return p.result(out), time.perf_counter() - t0


def tried(label, bid, method, *args):
    """``solve(...)``, or None with an ERROR line: a backend's fault costs only its own row."""
    try:
        return solve(*args)
    except Exception as exc:
        print(f"{label} {bid} {method} ERROR {type(exc).__name__}: {str(exc)[:160]}", flush=True)
        return None


def line(scene, bid, method, res, wall, **bad):
    print(f"{scene:9s} {bid:11s} {method:14s} {wall:7.3f}s {res.status_counts()} "
          + " ".join(f"{k}={v}" for k, v in bad.items()), flush=True)


def main():
    ids = sys.argv[1].split(",")
    side = int(sys.argv[2]) if len(sys.argv) > 2 else 256
    backends = {}
    for bid in ids:
        b = registry.resolve(bid)
        if getattr(b, "reason", None) or not hasattr(b, "prepare"):
            print(bid, "unavailable:", getattr(b, "reason", b), flush=True)
            continue
        backends[bid] = b
    eps32 = float(np.finfo(np.float32).eps)
    for seed in (0, 1):
        base, o, d = thin_walls(seed, side)
        scene = Transform(base, None, (1e4, 0.0, 0.0))
        of = o + np.array([1e4, 0.0, 0.0])
        exact = scene.first_hit(of, d, 0.0)
        mag = np.abs(of).sum(axis=1) + rounding_scale(scene)
        delta = 32.0 * eps32 * (np.abs(np.where(np.isfinite(exact), exact, 0.0)) + mag) + 4.0 * eps32 * 10.0
        for bid, b in backends.items():
            for method in ("sphere_trace", "hybrid_secant"):
                got = tried(f"far32.{seed}", bid, method, b, method, scene, of, d, "float32", 10.0)
                if got is None:
                    continue
                res, wall = got
                conv = res.status == Status.CONVERGED
                err = np.abs(res.t[conv] - exact[conv])
                line(f"far32.{seed}", bid, method, res, wall,
                     conv_beyond_delta=int(np.sum(~(err <= delta[conv]))),
                     worst_over_delta=round(float(np.max(err / delta[conv])), 3) if conv.any() else 0.0,
                     miss_on_hit=int(np.sum((res.status == Status.MISS) & np.isfinite(exact))))
        intervals = base.ray_intervals(o, d)
        for bid, b in backends.items():
            for method in ("sphere_trace", "hybrid_secant"):
                got = tried(f"walls64.{seed}", bid, method, b, method, base, o, d, "float64", 10.0)
                if got is None:
                    continue
                res, wall = got
                line(f"walls64.{seed}", bid, method, res, wall,
                     wrong=guarantee(intervals, res, 1e-10 if method == "sphere_trace" else 1e-4, 10.0))
        if seed == 1:
            liar = DeclaredLipschitz(Scaled(base, 4.0), 1.0)
            for bid, b in backends.items():
                for method in ("sphere_trace", "hybrid_secant"):
                    got = tried("liar", bid, method, b, method, liar, o, d, "float64", 10.0)
                    if got is None:
                        continue
                    res, wall = got
                    line("liar", bid, method, res, wall,
                         certified=int(np.sum((res.status == Status.CONVERGED) | (res.status == Status.MISS))))
    case = get_case("sphere.camera.64x64")
    ref = registry.resolve("numpy")
    p = ref.prepare("sphere_trace", case.scene, case.origins, case.directions, dtype="float32",
                    t_min=case.t_min, t_max=case.t_max)
    want = p.result(p.run())
    for bid, b in backends.items():
        res, wall = solve(b, "sphere_trace", case.scene, case.origins, case.directions, "float32", case.t_max)
        line("sphere32", bid, "sphere_trace", res, wall,
             status_differs_from_numpy=int(np.sum(res.status != want.status)),
             conv_err_max=float(np.max(np.abs(res.t - case.exact_t)[res.status == Status.CONVERGED])))


if __name__ == "__main__":
    main()
