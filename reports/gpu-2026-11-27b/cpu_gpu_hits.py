"""hybrid_secant on jax:gpu against jax:cpu, per ray: how many statuses, iteration and evaluation
counts differ, and the largest depth difference where both converged.

    python reports/gpu-2026-11-27b/cpu_gpu_hits.py > cpu_gpu_hits.txt
"""

import numpy as np

from impls import Status, registry
from impls.jax.backend import JaxBackend
from reference import get_case

registry.resolve("jax:gpu")
gpu, cpu = JaxBackend("gpu"), JaxBackend("cpu")
for cid in ("torus.camera.32x32", "mlp.camera.32x32", "sphere.grazing.1e-6", "csg.union.camera.32x32"):
    case = get_case(cid)
    r = {}
    for name, b in (("gpu", gpu), ("cpu", cpu)):
        p = b.prepare("hybrid_secant", case.scene, case.origins, case.directions, t_min=case.t_min, t_max=case.t_max)
        r[name] = p.result(p.run())
    g, c = r["gpu"], r["cpu"]
    st = g.status != c.status
    both = (g.status == Status.CONVERGED) & (c.status == Status.CONVERGED)
    pairs = sorted({(Status(int(a)).name, Status(int(b)).name) for a, b in zip(c.status[st], g.status[st])})
    print(f"{cid:24s} rays {len(g.t)}: status differs {int(st.sum())} {pairs}; iterations differ "
          f"{int((g.iterations != c.iterations).sum())}; evals differ {int((g.evals != c.evals).sum())}; "
          f"max |t_gpu - t_cpu| where both CONVERGED {np.max(np.abs(g.t[both] - c.t[both]), initial=0.0):.1e}")
