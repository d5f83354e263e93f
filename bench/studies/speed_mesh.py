"""Engines and root finders on mesh cameras (``python -m bench speed --mesh``): time × the closed-form unit
and depth error, side by side on the same rays.

The three stored meshes (:mod:`reference.mesh_cases`: torus, fin, blob) seen by a pinhole camera of
``side``² rays from the eye and field of view of their catalog cameras (``mesh.<name>.camera.32x32``;
the torus' is also the catalog's ``mesh.torus.camera.256x256`` and ``1024x1024``).  Each backend
answers every camera with ``raycast`` in float32 where it offers it (the engines: ``embree``,
``open3d``, …), else with the root finder ``method`` (default ``hybrid_secant``) in float64 at its
default knobs; the peer ``trimesh+embreex`` (trimesh's default intersector when embreex is
installed) answers too.  Scored as :mod:`bench.speed` scores the analytic scenes:

* time as a multiple of the *unit*, the closed-form ray–sphere intersection of the same rays in
  numpy (:func:`bench.studies.speed.unit_timer`), timed next to every call (:func:`bench.run.timing.times_against_unit`);
  the engine's BVH build is ``compile_s``, apart;
* depth error against the exact float64 first hit (:class:`reference.cases.Case` answers: the
  watertight ray–triangle hits of :class:`reference.mesh.MeshSDF`) over the rays the reference
  judges, false hits and false misses there, rays flagged with a failure status (not a wrong
  answer), and the rays the reference does not judge.

Each row records the backend's library versions.  This module reports; it asserts nothing about
speed (performance lives in benchmarks, not in tests).
"""

from __future__ import annotations

import importlib.metadata
import importlib.util
import json

import numpy as np

#: mesh → camera (eye, field of view) of its catalog camera case
CAMERAS = {"torus": ((0.0, -2.5, 1.8), 40.0), "fin": ((1.6, -1.9, 1.5), 40.0), "blob": ((0.0, 0.0, 3.0), 50.0)}
DEFAULT_BACKENDS = ("numpy", "embree", "open3d", "warp", "mitsuba")
PEER = "trimesh+embreex"


def cameras(n_side: int, meshes=tuple(CAMERAS)) -> dict:
    """``{mesh name: Case}``: the mesh seen by ``n_side``² pinhole rays from its catalog camera."""
    from reference.cases import _cam, make_case
    from reference.mesh_cases import stored_mesh

    out = {}
    for name in meshes:
        mesh = stored_mesh(name)
        eye, fov = CAMERAS[name]
        o, d = _cam(n_side, eye=eye, fov=fov)
        out[name] = make_case(f"mesh.{name}.camera.{n_side}x{n_side}", mesh, o, d, tags=("camera",),
                              description=f"{name} mesh, {n_side}² camera")
    return out


def _score(t: np.ndarray, flagged: np.ndarray, case) -> dict:
    exact, judged = case.exact_t, case.judged_mask
    hit, got = np.isfinite(exact), np.isfinite(t)
    both = judged & hit & got
    err = np.abs(t[both] - exact[both])
    return {"err_max": float(err.max()) if err.size else float("nan"),
            "false_hits": int(np.sum(judged & got & ~hit)), "false_misses": int(np.sum(judged & hit & ~got & ~flagged)),
            "flagged": int(np.sum(judged & flagged)), "not_judged": int(np.sum(~judged))}


def measure(backend_ids, n_side: int = 1024, method: str = "hybrid_secant", repeats: int = 3, peers: bool = True,
            meshes=tuple(CAMERAS), notes: list | None = None, progress=None) -> list[dict]:
    """One row per mesh camera × backend (and × peer), module docstring.  A backend that cannot run
    (unavailable, or offering neither raycast nor ``method``) is a line in ``notes``; one that
    raises on a camera is a row with its ``error``."""
    from .edges import resolve_engine

    notes = [] if notes is None else notes
    cams = cameras(n_side, meshes)
    runs = []  # (mesh, row, t, flagged)
    for bid in backend_ids:
        engine = resolve_engine(bid, method, notes)
        if engine is None:
            continue
        b, m, dtype = engine
        versions = json.dumps(b.versions(), sort_keys=True)
        for name, case in cams.items():
            if progress:
                progress(f"speed --mesh: {bid} {m} {dtype} on {case.id}")
            row = {"scene": case.id, "backend": bid, "method": m, "dtype": dtype, "rays": case.n_rays,
                   "versions": versions}
            runs.append((name, *_time_backend(b, m, dtype, case, row, repeats)))
    if peers:
        runs += _peer_runs(cams, repeats, notes, progress)
    rows = []
    for name, row, t, flagged in runs:  # every call timed before any exact answer is computed
        rows.append(row if t is None else {**row, **_score(t, flagged, cams[name])})
    return rows


def _time_backend(b, method: str, dtype: str, case, row: dict, repeats: int):
    """``(row, t, flagged)`` of ``b`` running ``method`` on ``case``, timed against the unit (t: the
    CONVERGED depths, +inf elsewhere); ``(row with error, None, None)`` when it raises."""
    from impls import Status

    from .speed import time_prepared

    try:
        # copies: a backend writing into its inputs must not change the case (read-only) for the next
        p = b.prepare(method, case.scene, np.array(case.origins), np.array(case.directions), dtype=dtype,
                      t_min=case.t_min, t_max=case.t_max)
        first, times, units, ratios, out = time_prepared(b, p, case.origins, case.directions, repeats)
        r = p.result(out)
    except Exception as exc:  # one backend's failure is its row
        return {**row, "error": f"{type(exc).__name__}: {exc}"[:300]}, None, None
    status = np.asarray(r.status)
    t = np.where(status == Status.CONVERGED, np.asarray(r.t, np.float64), np.inf)
    flagged = (status != Status.CONVERGED) & (status != Status.MISS)
    return ({**row, "time_s": float(np.median(times)), "unit_s": float(np.median(units)),
             "x_unit": float(np.median(ratios)), "compile_s": p.compile_s, "first_call_s": first, "error": ""},
            t, flagged)


def _peer_runs(cams: dict, repeats: int, notes: list, progress) -> list:
    """The trimesh+embreex peer's ``(mesh, row, t, flagged)`` per camera ([] and a note without embreex)."""
    from ..run.timing import times_against_unit
    from .edges import trimesh_embree_first_hits
    from .speed import unit_timer

    if importlib.util.find_spec("embreex") is None:
        notes.append(f"{PEER}: skipped: embreex is not installed (pip install -c constraints.txt -e '.[engines]')")
        return []
    versions = json.dumps({"trimesh": importlib.metadata.version("trimesh"),
                           "embreex": importlib.metadata.version("embreex")}, sort_keys=True)
    runs = []
    for name, case in cams.items():
        if progress:
            progress(f"speed --mesh: {PEER} on {case.id}")

        def call(case=case):
            return trimesh_embree_first_hits(case.scene, case.origins, case.directions)

        row = {"scene": case.id, "backend": f"peer:{PEER}", "method": "intersects_location",
               "dtype": "float32", "rays": case.n_rays, "versions": versions}
        try:
            times, units, ratios, t = times_against_unit(call, unit_timer(case.origins, case.directions), repeats)
        except Exception as exc:  # the peer's failure is its row
            runs.append((name, {**row, "error": f"{type(exc).__name__}: {exc}"[:300]}, None, None))
            continue
        runs.append((name, {**row, "time_s": float(np.median(times)), "unit_s": float(np.median(units)),
                            "x_unit": float(np.median(ratios)), "compile_s": None, "first_call_s": None,
                            "error": ""}, np.asarray(t, np.float64), np.zeros(case.n_rays, bool)))
    return runs


def format_rows(rows: list[dict]) -> str:
    """The rows as a markdown table, camera by camera."""
    import pandas as pd

    df = pd.DataFrame(rows)
    cols = [c for c in ("scene", "backend", "method", "dtype", "time_s", "x_unit", "err_max", "false_hits",
                        "false_misses", "flagged", "not_judged", "compile_s", "error") if c in df]
    df = df.iloc[np.argsort(pd.Categorical(df["scene"], categories=list(dict.fromkeys(df["scene"]))).codes,
                            kind="stable")]
    return df[cols].to_markdown(index=False, floatfmt=".3g")


def versions_line(rows: list[dict]) -> str:
    """``backend: lib version, …`` per backend, one line."""
    seen = {}
    for r in rows:
        seen.setdefault(r["backend"], r.get("versions", "{}"))
    return "; ".join(f"{b}: " + ", ".join(f"{k} {v}" for k, v in json.loads(v).items()) for b, v in seen.items())
