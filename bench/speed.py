"""Throughput of the root finders at scale: the measurement behind the backends issue's speed
targets (``python -m bench speed``).

2^20 pinhole rays (1024²) at two scenes, float64: the unit sphere seen from (0, 0, 3) with a
40° field of view, and the torus ∪ box of case ``csg.union.camera.32x32`` from that case's
eye with 45°.  Each backend runs one root method (default ``hybrid_secant`` at its default
knobs) and is scored on

* depth error against the exact first hit (closed forms; the torus by its quartic), its
  maximum and the number of rays above 1e-6, false hits and false misses;
* time as a multiple of the *unit*: the exact closed-form ray–sphere intersection of the same
  rays in numpy (b = ⟨o, d⟩, c = |o|² − 1, t = −b − √(b² − c)), timed right before every run
  so that both see the same machine load (medians of ``repeats`` runs; the unit's own median
  of 3 each time).

Compile time (jax) and the first call are reported apart.  The targets the issue sets are
``TARGETS``; this module reports, it does not assert (performance lives in benchmarks, not in
tests).
"""

from __future__ import annotations

import time

import numpy as np

TARGETS = {"numpy": 30.0, "jax:cpu": 20.0, "torch:cpu": 60.0}


def lean_sphere_hits(o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """First hit of the unit sphere at the origin, |d| = 1 (the time unit; not the cancellation-
    free reference formula, which is slower: this is the fastest honest closed form)."""
    b = np.einsum("ij,ij->i", o, d)
    c = np.einsum("ij,ij->i", o, o) - 1.0
    disc = b * b - c
    return np.where(disc >= 0, -b - np.sqrt(np.maximum(disc, 0)), np.inf)


def scenes(n_side: int):
    """``{name: (scene, origins, directions)}`` of the two scenes with n_side² rays."""
    from reference import Sphere
    from reference.cases import get_case
    from reference.rays import pinhole

    union = get_case("csg.union.camera.32x32")
    return {
        "sphere": (Sphere(),) + pinhole(eye=(0, 0, 3.0), look_at=(0, 0, 0), fov_deg=40, width=n_side, height=n_side),
        "torus∪box": (union.scene,) + pinhole(eye=tuple(union.origins[0]), look_at=(0, 0, 0), fov_deg=45,
                                               width=n_side, height=n_side),
    }


def _median_time(fn, k: int) -> float:
    ts = []
    for _ in range(k):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def measure(backend_ids, n_side: int = 1024, method: str = "hybrid_secant", repeats: int = 3, knobs=None,
            t_max: float = 10.0) -> list[dict]:
    """One row per scene × backend (see the module docstring)."""
    from impls import Status, registry

    rows = []
    for name, (scene, o, d) in scenes(n_side).items():
        exact = scene.first_hit(o, d, 0.0)
        exact = np.where(exact <= t_max, exact, np.inf)
        hit = np.isfinite(exact)
        for bid in backend_ids:
            b = registry.resolve(bid)
            p = b.prepare(method, scene, o, d, t_min=0.0, t_max=t_max, **(knobs or {}))
            t0 = time.perf_counter()
            out = p.run()
            b.synchronize(out)
            first = time.perf_counter() - t0
            ratios, times, units = [], [], []
            for _ in range(repeats):
                unit = _median_time(lambda: lean_sphere_hits(o, d), 3)
                t0 = time.perf_counter()
                out = p.run()
                b.synchronize(out)
                dt = time.perf_counter() - t0
                times.append(dt)
                units.append(unit)
                ratios.append(dt / unit)
            r = p.result(out)
            got = r.status == Status.CONVERGED
            err = np.abs(r.t[hit & got] - exact[hit & got])
            rows.append({
                "scene": name, "backend": bid, "method": method, "rays": int(o.shape[0]),
                "time_s": float(np.median(times)), "unit_s": float(np.median(units)),
                "x_unit": float(np.median(ratios)), "x_unit_min": float(np.min(ratios)),
                "x_unit_max": float(np.max(ratios)), "target": TARGETS.get(bid),
                "compile_s": p.compile_s, "first_call_s": first,
                "err_max": float(err.max()) if err.size else float("nan"), "n_err_gt_1e-6": int((err > 1e-6).sum()),
                "false_hits": int((got & ~hit).sum()), "false_misses": int((hit & ~got).sum()),
                "evals_mean": float(r.evals.mean()), "evals_max": int(r.evals.max()),
                "status_counts": {int(s): int(c) for s, c in zip(*np.unique(r.status, return_counts=True))},
            })
    return rows


def format_rows(rows: list[dict]) -> str:
    import pandas as pd

    df = pd.DataFrame(rows)
    cols = ["scene", "backend", "time_s", "x_unit", "x_unit_min", "x_unit_max", "target", "err_max", "n_err_gt_1e-6",
            "false_hits", "false_misses", "evals_mean", "evals_max", "compile_s"]
    return df[cols].to_markdown(index=False, floatfmt=".3g")
