"""Certified answers at the ray counts users render, on any backends (here: the GPU ones).

    python reports/gpu-2026-11-28/certified_gpu.py BACKENDS [SIDE_SCALE [GROUPS]]

Counts, per backend, method and dtype, the certified answers that are wrong against an exact
(or, for a user's callable field, a numerical) first hit:
  * ``wrong-conv``: CONVERGED more than ``tol`` off the first crossing (or where there is none);
  * ``wrong-miss``: MISS where a crossing exists in [t_min, t_max].
Three groups of scenes, none in the case catalog:
  1. understated Lipschitz bounds: 12 random unions (thin torus, thin spherical shell, thin disk)
     scaled by k = 1.05..3 and declared L = 1 (``DeclaredLipschitz``), 128² rays each;
  2. ``mesh.fin``'s camera widened to 1024² (2^20 rays), exact hits by the mesh's triangles;
  3. a user's ``CallableField`` (a ripple sphere, honest L = 1.7) at 256² against the numerical
     reference (``first_hit_numeric``: rays it flags are not judged).
SIDE_SCALE (default 1) divides the ray-image sides, for a dry run on a CPU; GROUPS (default
``liars,fin,user``) picks the groups."""
import sys
import time

import numpy as np

sys.path.insert(0, ".")
from impls import registry  # noqa: E402
from impls.protocol import Status  # noqa: E402
from reference import (CallableField, CappedCylinder, Difference, Scaled, Sphere, Torus, Transform,  # noqa: E402
                       Union, rays)
from reference.cases import DeclaredLipschitz, get_case  # noqa: E402
from reference.numerical import first_hit_numeric  # noqa: E402

BACKENDS = sys.argv[1].split(",")
SCALE = int(sys.argv[2]) if len(sys.argv) > 2 else 1
GROUPS = sys.argv[3].split(",") if len(sys.argv) > 3 else ["liars", "fin", "user"]
METHODS = ("sphere_trace", "hybrid_secant")


def liars():
    rng = np.random.default_rng(5)
    side = 128 // SCALE
    for k in (1.05, 1.3, 2.0, 3.0):
        for j in range(3):
            parts = [Transform.from_rotvec(Torus(float(rng.uniform(.3, .5)), float(rng.uniform(.01, .05))),
                                           tuple(rng.normal(size=3)), tuple(rng.uniform(-.3, .3, 3))),
                     Difference(Sphere((0, 0, 0), 0.45), Sphere((0, 0, 0), 0.45 - float(rng.uniform(0.005, 0.03)))),
                     Transform.from_rotvec(CappedCylinder(float(rng.uniform(.2, .5)), float(10 ** rng.uniform(-2.5, -1.5))),
                                           tuple(rng.normal(size=3)), tuple(rng.uniform(-.4, .4, 3)))]
            child = Scaled(Union(*parts), k)
            eye = rng.normal(size=3)
            eye = eye / np.linalg.norm(eye) * rng.uniform(1.0, 4.0)
            o, d = rays.pinhole(eye=tuple(eye), look_at=(0, 0, 0), fov_deg=50, width=side, height=side)
            iv = child.ray_intervals(o, d)
            first = np.array([x[0] if x.size else np.inf for x in iv])
            first = np.where(first <= 10.0, first, np.inf)
            yield f"liar.k{k}-{j}", DeclaredLipschitz(child, 1.0), o, d, 0.0, 10.0, first, np.zeros_like(first)


def fin():
    case = get_case("mesh.fin.camera.32x32")
    side = 1024 // SCALE
    o, d = rays.pinhole(eye=tuple(case.origins[0]), look_at=(0, 0, 0), fov_deg=40.0, width=side, height=side)
    first = case.scene.first_hit(o, d, 0.0)
    first = np.where(first <= case.t_max, first, np.inf)
    yield f"mesh.fin.{side}x{side}", case.scene, o, d, 0.0, case.t_max, first, np.zeros_like(first)


def ripple(x, xp):  # |∇φ| ≤ 1 + 0.05·8·√3 ≈ 1.69
    r = xp.sqrt(xp.sum(x * x, axis=-1))
    return r - 0.8 + 0.05 * xp.sin(8 * x[..., 0]) * xp.sin(8 * x[..., 1]) * xp.sin(8 * x[..., 2])


def user():
    side = 256 // SCALE
    field = CallableField(ripple, lipschitz=1.7, name="gpu.ripple")
    o, d = rays.pinhole(eye=(2.2, -0.4, 1.0), look_at=(0.1, 0, 0), up=(0, 0, 1), fov_deg=60, width=side, height=side)
    t0 = time.time()
    first, err = first_hit_numeric(field, o, d, 0.1, 5.0)
    print(f"# numerical reference {side}x{side}: {time.time() - t0:.1f} s, {int(np.isnan(err).sum())} rays flagged",
          flush=True)
    yield f"user.ripple.{side}x{side}", field, o, d, 0.1, 5.0, first, err


def judge(name, scene, o, d, t_min, t_max, first, err, backend, method, dtype):
    tol = 1e-9 if dtype == "float64" else float(np.sqrt(np.finfo(np.float32).eps))
    try:
        p = backend.prepare(method, scene, o.copy(), d.copy(), dtype=dtype, t_min=t_min, t_max=t_max)
        t0 = time.perf_counter()
        r = p.result(p.run())
        el = time.perf_counter() - t0
        t0 = time.perf_counter()
        p.result(p.run())  # again: the first run holds jax's compile
        el2 = time.perf_counter() - t0
    except Exception as exc:  # a backend's fault is a row, not the end of the run
        print(f"{name:22s} {backend.id:9s} {method:13s} {dtype:7s} FAILED {type(exc).__name__}: {str(exc)[:120]}")
        return 0
    st, t = np.asarray(r.status), np.asarray(r.t, dtype=np.float64)
    judged = np.isfinite(err) & ~np.isnan(first)
    conv = (st == Status.CONVERGED) & judged
    off = conv & ~(np.abs(t - first) <= tol * np.maximum(1.0, np.abs(np.where(np.isfinite(first), first, 0))))
    bad_miss = (st == Status.MISS) & judged & np.isfinite(first)
    cnt = {Status(int(k)).name: int(v) for k, v in zip(*np.unique(st, return_counts=True))}
    print(f"{name:22s} {backend.id:9s} {method:13s} {dtype:7s} rays {st.size:8d} not-judged {int((~judged).sum()):6d} "
          f"wrong-conv {int(off.sum()):5d} wrong-miss {int(bad_miss.sum()):5d} evals/ray {np.mean(r.evals):7.2f} "
          f"run {el:7.3f} s, again {el2:7.3f} s {cnt}", flush=True)
    return int(off.sum() + bad_miss.sum())


def main():
    backends = [registry.resolve(b) for b in BACKENDS]
    wrong = 0
    t_start = time.time()
    for group, dtypes in ((liars, ("float64",)), (fin, ("float64", "float32")), (user, ("float64", "float32"))):
        if group.__name__ not in GROUPS:
            continue
        for name, scene, o, d, t_min, t_max, first, err in group():
            for b in backends:
                for m in METHODS:
                    for dt in dtypes:
                        wrong += judge(name, scene, o, d, t_min, t_max, first, err, b, m, dt)
    print(f"# total wrong certified answers: {wrong}; wall {time.time() - t_start:.0f} s")


if __name__ == "__main__":
    main()
