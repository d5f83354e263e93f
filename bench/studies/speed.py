"""Throughput of the root finders at scale, against the speed targets of :data:`TARGETS`
(``python -m bench speed``).

2^20 pinhole rays (1024²) at two scenes, float64: the unit sphere seen from (0, 0, 3) with a
40° field of view, and the torus ∪ box of case ``csg.union.camera.32x32`` from that case's
eye with 45°.  Each backend runs one root method (default ``hybrid_secant`` at its default
knobs) and is scored on

* depth error against the exact first hit (closed forms; the torus by its quartic), its
  maximum and the number of rays above 1e-6, false hits and false misses;
* time as a multiple of the *unit*: the exact closed-form ray–sphere intersection of the same
  rays in numpy (b = ⟨o, d⟩, c = |o|² − 1, t = −b − √(b² − c), into preallocated arrays:
  :func:`lean_sphere_hits`), timed right before every run so that both see the same machine
  load (medians of ``repeats`` runs; the unit's own median of 3 each time).

Compile time (jax) and the first call are reported apart.  :data:`TARGETS` are the
multiples of the unit each backend aims at; this module reports, it does not assert (performance lives in benchmarks, not in
tests).
"""

from __future__ import annotations

import time

import numpy as np

from ..run.timing import times_against_unit

#: the multiple of the unit each backend aims at on the sphere
TARGETS = {"numpy": 30.0, "jax:cpu": 20.0, "torch:cpu": 60.0}


def lean_sphere_hits(o: np.ndarray, d: np.ndarray, out: np.ndarray | None = None,
                     work: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """First hit of the unit sphere at the origin, |d| = 1 (the time unit).

    Not the cancellation-free reference formula, which is slower: the fastest honest closed
    form on (n, 3) rays.  With ``out`` and ``work`` (three float64 arrays of n) it allocates
    nothing, which is how :func:`measure` times it: a fresh large temporary costs page faults
    whose price depends on the allocator's state (what else the process imported and freed),
    and the unit must not move with it.  Either way it returns
    t = −b − √(b² − c), b = ⟨o, d⟩, c = |o|² − 1, and inf where b² − c < 0."""
    n = o.shape[0]
    t = np.empty(n) if out is None else out
    b, c = (np.empty(n), np.empty(n)) if work is None else work
    np.einsum("ij,ij->i", o, d, out=b)
    np.einsum("ij,ij->i", o, o, out=c)
    c -= 1.0
    np.multiply(b, b, out=t)
    np.subtract(t, c, out=c)  # the discriminant
    ok = c >= 0
    np.sqrt(c, out=c, where=ok)
    np.add(b, c, out=t)
    np.negative(t, out=t)
    t[~ok] = np.inf
    return t


def unit_timer(o: np.ndarray, d: np.ndarray):
    """A no-argument callable timing one allocation-free :func:`lean_sphere_hits` of these rays."""
    bufs = [np.empty(o.shape[0]) for _ in range(3)]
    return lambda: lean_sphere_hits(o, d, bufs[0], (bufs[1], bufs[2]))


def time_prepared(b, p, o: np.ndarray, d: np.ndarray, repeats: int):
    """``(first call s, times, units, ratios, output)`` of the prepared method ``p`` of backend ``b``:
    one synchronised first call (compilation, warm-up) timed apart, then ``repeats`` synchronised
    calls each beside the closed-form unit of the same rays (:func:`times_against_unit`)."""
    t0 = time.perf_counter()
    out = p.run()
    b.synchronize(out)
    first = time.perf_counter() - t0

    def call():
        res = p.run()
        b.synchronize(res)
        return res

    times, units, ratios, out = times_against_unit(call, unit_timer(o, d), repeats)
    return first, times, units, ratios, out


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


def measure(backend_ids, n_side: int = 1024, method: str = "hybrid_secant", repeats: int = 3, knobs=None,
            t_max: float = 10.0, threads: int = 1, peers: bool = False, notes: list | None = None) -> list[dict]:
    """One row per scene × backend (see the module docstring), and with ``peers`` one per scene ×
    peer (:mod:`bench.studies.peers`: a numba per-ray sphere tracer, scipy's Chandrupatla), timed after
    the backends and scored the same way; a peer that cannot run here is a line in ``notes``.

    Backends run one after the other, each on every scene (jax, last by default, leaves XLA's
    worker threads behind), and every run is timed before any exact hit is computed (the
    exact torus hits make about a million small arrays), so that neither disturbs the
    timings.  With the default allocator a backend's time still depends on which ran before it
    (the heap they left); :func:`bench.run.environment.tune_allocator` removes that dependence."""
    from impls import Status, registry

    from ..run.environment import configure_driver

    runs = []
    cases = scenes(n_side)
    for bid in backend_ids:
        b = registry.resolve(bid)
        configure_driver(b, threads)
        for name, (scene, o, d) in cases.items():
            # copies: a backend writing into its inputs must not change the next backend's rays
            p = b.prepare(method, scene, o.copy(), d.copy(), t_min=0.0, t_max=t_max, **(knobs or {}))
            first, times, units, ratios, out = time_prepared(b, p, o, d, repeats)
            runs.append((name, bid, b.id, p.result(out), {
                "scene": name, "backend": bid, "method": method, "rays": int(o.shape[0]),
                "time_s": float(np.median(times)), "unit_s": float(np.median(units)),
                "x_unit": float(np.median(ratios)), "x_unit_min": float(np.min(ratios)),
                "x_unit_max": float(np.max(ratios)), "target": TARGETS.get(b.id),
                "compile_s": p.compile_s, "first_call_s": first}))
    if peers:
        from .peers import root_peer_runs

        peer_runs, skipped = root_peer_runs(cases, repeats, t_max, unit_timer)
        runs += [(name, label, label, r, row) for name, label, r, row in peer_runs]
        if notes is not None:
            notes.extend(skipped)
    rows = []
    exact_of = {}
    for name, _, _, r, row in runs:
        if name not in exact_of:
            scene, o, d = cases[name]
            exact = scene.first_hit(o, d, 0.0)
            exact_of[name] = np.where(exact <= t_max, exact, np.inf)
        exact = exact_of[name]
        hit = np.isfinite(exact)
        got = r.status == Status.CONVERGED
        # flagged: neither a hit nor a miss is claimed (UNCERTIFIED, MAX_ITER, …); a false miss is a
        # MISS where the exact answer hits, as in bench.studies.speed_mesh
        flagged = ~got & (r.status != Status.MISS)
        err = np.abs(r.t[hit & got] - exact[hit & got])
        rows.append(dict(row, **{
            "err_max": float(err.max()) if err.size else float("nan"), "n_err_gt_1e-6": int((err > 1e-6).sum()),
            "false_hits": int((got & ~hit).sum()), "false_misses": int((hit & ~got & ~flagged).sum()),
            "flagged": int(flagged.sum()),
            "evals_mean": float(r.evals.mean()), "evals_max": int(r.evals.max()),
            "status_counts": {int(s): int(c) for s, c in zip(*np.unique(r.status, return_counts=True))},
        }))
    return rows


def format_rows(rows: list[dict]) -> str:
    import pandas as pd

    df = pd.DataFrame(rows)
    df = df.iloc[np.argsort(pd.Categorical(df["scene"], categories=list(dict.fromkeys(df["scene"]))).codes,
                            kind="stable")]  # scene by scene, backends in run order
    cols = ["scene", "backend", "time_s", "x_unit", "x_unit_min", "x_unit_max", "target", "err_max", "n_err_gt_1e-6",
            "false_hits", "false_misses", "flagged", "evals_mean", "evals_max", "compile_s"]
    return df[cols].to_markdown(index=False, floatfmt=".3g")
