"""jax's two-kernel methods on a GPU: render_surface (hybrid_secant's kernel, then a shading
kernel) and the volume renderers with bins fixed up front (a sampler kernel, then the density
model's shading kernel), against the same methods compiled as one kernel each, on jax:gpu, and
against jax:cpu.  Prints one line per case × method: compile seconds (two kernels / one), run
medians, whether statuses and counts are equal, and the largest |Δ| of the float outputs.

    python reports/gpu-2026-11-27b/chains.py > chains.txt
"""

from __future__ import annotations

import time

import numpy as np

from impls import registry
from impls.core.table import METHOD_TABLE
from impls.jax.backend import JaxBackend
from reference import get_case

registry.resolve("jax:gpu")  # float64 on
METHODS = ["render_surface"] + [f"volume_{m}_{s}" for m in ("nerf", "neus", "unisurf", "volsdf")
                                for s in ("uniform", "stratified", "band", "importance")]


def prepared(backend, method, case):
    kw = {"t_hit": np.where(case.hit_mask, case.exact_t, np.inf)} if method.endswith("band") else {}
    t0 = time.perf_counter()
    p = backend.prepare(method, case.scene, case.origins, case.directions, t_min=case.t_min, t_max=case.t_max, **kw)
    out = p.run()
    backend.synchronize(out)
    return p, time.perf_counter() - t0


def median_run(backend, p, k=9):
    ts = []
    for _ in range(k):
        t0 = time.perf_counter()
        backend.synchronize(p.run())
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def fused(method):
    """A context in which ``method`` compiles as one kernel (its parts' attributes hidden)."""
    impl = METHOD_TABLE[method]
    saved = {a: getattr(impl, a) for a in ("stages", "hit_method") if hasattr(impl, a)}

    class Ctx:
        def __enter__(self):
            for a in saved:
                delattr(impl, a)

        def __exit__(self, *exc):
            for a, v in saved.items():
                setattr(impl, a, v)

    return Ctx()


def diff(a, b):
    same = all(np.array_equal(getattr(a, k), getattr(b, k)) for k in ("status", "iterations", "evals"))
    worst = 0.0
    for x, y in [(a.t, b.t), *((a.outputs[k], b.outputs[k]) for k in b.outputs)]:
        x, y = np.asarray(x, float), np.asarray(y, float)
        fin = np.isfinite(x) & np.isfinite(y)
        same &= bool(np.array_equal(np.isfinite(x), np.isfinite(y)))
        if fin.any():
            worst = max(worst, float(np.max(np.abs(x[fin] - y[fin]))))
    return same, worst


def main():
    gpu, one, cpu = JaxBackend("gpu"), JaxBackend("gpu"), JaxBackend("cpu")
    for b in (gpu, one, cpu):
        b._store = None
    print("device", gpu.jax_device, "| cpu", cpu.jax_device)
    for cid in ("torus.camera.32x32", "mlp.camera.32x32", "sphere.grazing.1e-6"):
        case = get_case(cid)
        for m in METHODS:
            if m == "render_surface":  # its hit kernel is hybrid_secant's: compiled with that method
                prepared(gpu, "hybrid_secant", case)
            p2, c2 = prepared(gpu, m, case)
            with fused(m):
                p1, c1 = prepared(one, m, case)
            pc, _ = prepared(cpu, m, case)
            r2, r1, rc = (p.result(p.run()) for p in (p2, p1, pc))
            s_one, d_one = diff(r2, r1)
            s_cpu, d_cpu = diff(r2, rc)
            print(f"{cid:22s} {m:26s} compile {c2:6.2f} s (one kernel {c1:6.2f} s)  run {median_run(gpu, p2) * 1e3:8.3f} ms "
                  f"(one kernel {median_run(one, p1) * 1e3:8.3f} ms)  vs one kernel: same={s_one} max|d|={d_one:.1e}  "
                  f"vs jax:cpu: same={s_cpu} max|d|={d_cpu:.1e}", flush=True)


if __name__ == "__main__":
    main()
