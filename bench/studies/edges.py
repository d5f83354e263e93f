"""The engines at the edge (``python -m bench edges``): wrong hits and misses against the grazing offset.

For each stored mesh of the case catalog (torus, fin, blob: :mod:`reference.mesh_cases`), three
families of rays that pass a feature at an offset δ · size (size: the mesh's bounding-box
diagonal), δ = 1e-2 … 1e-9, half of them just outside the solid and half just inside:

* ``edge`` — perpendicular to a random convex edge and to its mean normal, through the edge
  point ± δ · size along that normal (:func:`reference.mesh_cases.edge_grazing_rays`);
* ``vertex`` — through a random vertex ± δ · size along its normal (the normalised sum of its
  faces' angle-weighted normals), in a random direction perpendicular to that normal;
* ``parallel`` — in the plane of a random face, offset ± δ · size along its normal, through
  the point above or below its centroid (a ray parallel to a face: the case the engines'
  ray–triangle tests divide by ⟨n, d⟩ ≈ 0).

Every ray starts twice the bounding radius before that point, outside the mesh.  Truth is the
exact float64 first hit (:meth:`reference.mesh.MeshSDF.first_hit`); rays the reference flags
(no certified answer, :func:`reference.depthbound.depth_bounds` non-finite: a touch that float64
cannot tell from a near miss) are counted as ``not_judged`` and left out, as ``bench run``
leaves them out.  Each *engine* answers the same rays:

* a backend offering ``raycast`` (``embree``, ``open3d``, ``warp``, ``mitsuba``, and any other
  ``--backend`` adds): its float32 first hit;
* any other backend: the root finder ``--method`` (default ``hybrid_secant``, numpy) in float64
  at its default knobs (CONVERGED is a hit; any other status on a hitting ray is a miss, as
  ``bench run`` counts it);
* ``trimesh`` — trimesh's float64 ray–triangle narrow phase (``trimesh.ray.ray_triangle``), the
  truth-side check: a second float64 intersector that should agree with the reference;
* ``trimesh+embreex`` — trimesh's default intersector when embreex is installed
  (``trimesh.ray.ray_pyembree``, float32 Embree with trimesh's own offsets), the configuration
  users meet in trimesh.

Per (mesh, family, δ, engine): rays, judged rays, false hits (the engine hits, the reference
misses), false misses (the engine reports a MISS where the reference hits), flagged rays (a root
finder's failure status, e.g. UNCERTIFIED: "no answer", not a wrong one; engines never flag), the
hits off by more than the row's dtype's depth tolerance √ε · max(1, T) (T the largest exact depth
of the set, as the stability matrix judges: a hit on another surface), the wrong-answer rate
(false hits + false misses + off hits, over judged rays) and the largest depth error where both hit.  The summary table gives, per engine, mesh and
family, the *largest offset at which it first returns a wrong answer* scanning δ downward
("none down to 1e-9" when it never does), and the plot the rate and error against δ.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd

#: offsets δ (× the mesh's size) from far to near
DEFAULT_OFFSETS = tuple(10.0 ** -k for k in range(2, 10))
DEFAULT_MESHES = ("torus", "fin", "blob")
FAMILIES = ("edge", "vertex", "parallel")
DEFAULT_ENGINES = ("embree", "open3d", "warp", "mitsuba", "trimesh", "trimesh+embreex", "numpy")
#: the engines computed here rather than by a backend
TRIMESH, TRIMESH_EMBREE = "trimesh", "trimesh+embreex"
FILE, PLOT = "edges.csv", "edges.png"


# -- rays -----------------------------------------------------------------------------------------

def _perpendicular(n: np.ndarray, rng) -> np.ndarray:
    """A random unit vector perpendicular to each row of ``n`` (unit)."""
    from reference.rays import normalize

    r = rng.normal(size=n.shape)
    return normalize(r - np.einsum("ij,ij->i", r, n)[:, None] * n)


def _vertex_normals(mesh) -> np.ndarray:
    """Angle-weighted vertex normals (Thürmer & Wüthrich 1998), trimesh's ``vertex_normals``."""
    import trimesh

    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False, validate=False)
    return np.asarray(tm.vertex_normals, np.float64)


def feature_rays(mesh, family: str, n: int, offset: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` rays of ``family`` at ``offset`` (module docstring): even rays just outside, odd just
    inside; the same features for every offset of a seed (only the offset moves the rays)."""
    from reference.mesh_cases import edge_grazing_rays

    if family == "edge":
        return edge_grazing_rays(mesh, n, offset, seed)
    rng = np.random.default_rng(seed)
    s = np.where(np.arange(n) % 2 == 0, 1.0, -1.0)
    if family == "vertex":
        pick = rng.choice(len(mesh.vertices), n)
        p, nrm = mesh.vertices[pick], _vertex_normals(mesh)[pick]
    elif family == "parallel":
        pick = rng.choice(len(mesh.faces), n)
        p, nrm = mesh.vertices[mesh.faces[pick]].mean(axis=1), mesh.face_normals[pick]
    else:
        raise ValueError(f"family must be one of {FAMILIES}, got {family!r}")
    d = _perpendicular(nrm, rng)
    x = p + (s * offset * mesh.size)[:, None] * nrm
    return x - 2.0 * mesh.bounding_sphere()[1] * d, d


# -- the engines ------------------------------------------------------------------------------------

def trimesh_first_hits(mesh, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """First hit (t > 0) per ray by trimesh's float64 ray–triangle narrow phase, inf on a miss.

    Its broad phase wants an ``rtree`` index, which isobench does not install; a stand-in hands it,
    per ray, the faces whose padded bounding ball the ray's line meets (a superset of the faces
    the ray can hit, so the answer is trimesh's narrow phase's), as tests/test_mesh_trimesh_crosscheck.py
    does for the whole catalog."""
    import trimesh
    from trimesh.ray.ray_triangle import ray_triangle_id

    tri = mesh.vertices[mesh.faces]
    c = tri.mean(axis=1)
    r = np.max(np.linalg.norm(tri - c[:, None], axis=2), axis=1) * (1 + 1e-9) + 1e-12 * mesh.size
    per_ray = []
    for s in range(0, len(o), 256):
        w = c[None] - o[s:s + 256, None]
        along = np.einsum("rfk,rk->rf", w, d[s:s + 256])
        near = np.einsum("rfk,rfk->rf", w, w) - along ** 2 <= (r ** 2)[None] * (1 + 1e-9) + 1e-300
        per_ray.extend(np.flatnonzero(row) for row in near)

    class _Candidates:  # trimesh queries its tree once per ray, in order
        def __init__(self):
            self.bounds, self._it = np.concatenate([mesh.vertices.min(0), mesh.vertices.max(0)]), iter(per_ray)

        def intersection(self, _box):
            return next(self._it)

    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False, validate=False)
    _, ray, loc = ray_triangle_id(tm.triangles, o, d, triangles_normal=tm.face_normals, tree=_Candidates(),
                                  multiple_hits=True)
    t = np.einsum("ij,ij->i", loc - o[ray], d[ray]) if len(ray) else np.zeros(0)
    keep = t > 0
    first = np.full(len(o), np.inf)
    np.minimum.at(first, ray[keep], t[keep])
    return first


def trimesh_embree_first_hits(mesh, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """First hit per ray by trimesh's embreex intersector (its default when embreex is installed)."""
    import trimesh
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False, validate=False)
    loc, ray, _ = RayMeshIntersector(tm).intersects_location(o, d, multiple_hits=False)
    first = np.full(len(o), np.inf)
    if len(ray):
        np.minimum.at(first, ray, np.einsum("ij,ij->i", loc - o[ray], d[ray]))
    return first


def resolve_engine(bid: str, method: str, notes: list):
    """``(backend, method, dtype)`` that answers the first hit for ``bid``: its ``raycast`` in
    float32 where it offers one, else ``method`` in float64; None, with a line in ``notes``
    saying why, when the backend is unavailable or offers neither."""
    from impls import registry

    b = registry.resolve(bid)
    if isinstance(b, registry.Unavailable):
        notes.append(f"{bid}: skipped: {b.reason}")
        return None
    m, dtype = ("raycast", "float32") if "raycast" in b.methods() else (method, "float64")
    if m not in b.methods():
        notes.append(f"{bid}: skipped: it offers neither raycast nor {method}")
        return None
    return b, m, dtype


def engine_callables(ids: list[str], method: str = "hybrid_secant") -> tuple[dict[str, Callable], list[str]]:
    """``{engine: (f(mesh, o, d) -> first-hit depths (inf: a miss; NaN: a ray the method flagged with
    a failure status, no answer), the dtype it computes in)}`` for the engines that can run here,
    and a line per one that cannot (its reason).  An id is ``trimesh``, ``trimesh+embreex`` or a
    backend id (:mod:`impls.registry`): ``raycast`` in float32 where it offers it, else ``method``
    in float64 at default knobs."""
    import importlib.util

    from impls import Status

    out, notes = {}, []
    for eid in ids:
        if eid == TRIMESH:
            out[eid] = (trimesh_first_hits, "float64")
            continue
        if eid == TRIMESH_EMBREE:
            if importlib.util.find_spec("embreex") is None:
                notes.append(f"{eid}: skipped: embreex is not installed (pip install -c constraints.txt -e '.[engines]')")
            else:
                out[eid] = (trimesh_embree_first_hits, "float32")
            continue
        engine = resolve_engine(eid, method, notes)
        if engine is None:
            continue
        b, m, dtype = engine

        def run(mesh, o, d, b=b, m=m, dtype=dtype):
            prep = b.prepare(m, mesh, o, d, dtype=dtype, t_min=0.0, t_max=10.0 * mesh.size)
            out_ = prep.run()
            b.synchronize(out_)
            r = prep.result(out_)
            status = np.asarray(r.status)
            # a hit, inf for a reported MISS, NaN for a ray the method flagged (no answer: not a silent one)
            return np.where(status == Status.CONVERGED, np.asarray(r.t, np.float64),
                            np.where(status == Status.MISS, np.inf, np.nan))

        out[b.id if m == "raycast" else f"{b.id} · {m} · {dtype}"] = (run, dtype)
    return out, notes


# -- the study --------------------------------------------------------------------------------------

def check_arguments(meshes, offsets, families, n_rays) -> None:
    """A ValueError naming the option for anything the study cannot run."""
    from reference.make_meshes import SHAPES as MESHES

    unknown = [m for m in meshes if m not in MESHES]
    if not meshes or unknown:
        raise ValueError(f"--mesh: unknown mesh(es) {unknown or meshes}; stored meshes: {sorted(MESHES)}")
    if not offsets or any(not (math.isfinite(x) and 0 < x < 1) for x in offsets):
        raise ValueError(f"--offsets: {list(offsets)} must be numbers in (0, 1), e.g. 1e-2,1e-5,1e-9")
    bad = [f for f in families if f not in FAMILIES]
    if not families or bad:
        raise ValueError(f"--family: unknown family(ies) {bad or families}; choose from {list(FAMILIES)}")
    if n_rays < 2:
        raise ValueError(f"--rays: {n_rays} must be ≥ 2 (half outside, half inside)")


def edges_table(engines: dict[str, tuple[Callable, str]], meshes=DEFAULT_MESHES, families=FAMILIES, offsets=DEFAULT_OFFSETS,
                n_rays: int = 64, seed: int = 0, stage: Callable[[str], None] | None = None) -> pd.DataFrame:
    """One row per mesh × family × offset × engine (module docstring).  An engine that raises on
    a ray set gets a row with its ``error`` and no counts: a failing engine never stops the study."""
    from reference.depthbound import depth_bounds
    from reference.mesh_cases import stored_mesh

    from .stability import depth_tolerance

    rows = []
    for mi, name in enumerate(meshes):
        mesh = stored_mesh(name)
        for fi, family in enumerate(families):
            if stage:
                stage(f"edges {name} · {family}: {len(offsets)} offsets × {len(engines)} engines, {n_rays} rays each")
            for off in offsets:
                o, d = feature_rays(mesh, family, n_rays, off, seed + 1000 * mi + 100 * fi)
                exact = mesh.first_hit(o, d, 0.0)
                judged = np.isfinite(depth_bounds(mesh, o, d, exact))
                hit = np.isfinite(exact)
                scale = float(np.max(exact[hit], initial=1.0))
                for eng, (fn, dtype) in engines.items():
                    row = {"mesh": name, "family": family, "offset": off, "engine": eng, "rays": n_rays,
                           "judged": int(judged.sum()), "not_judged": int((~judged).sum())}
                    try:
                        t = np.asarray(fn(mesh, o, d), np.float64)
                    except Exception as exc:  # one engine's failure is its row, not the study's end
                        rows.append({**row, "error": f"{type(exc).__name__}: {exc}"[:300]})
                        continue
                    got, flagged = np.isfinite(t), np.isnan(t)
                    both = judged & hit & got
                    fh, fm = int(np.sum(judged & got & ~hit)), int(np.sum(judged & hit & (t == np.inf)))
                    tol = depth_tolerance(dtype, scale)
                    dev = np.abs(np.where(both, t, 0.0) - np.where(both, exact, 0.0))
                    n_off = int(np.sum(dev > tol))
                    rows.append({**row, "dtype": dtype, "tolerance": tol, "false_hits": fh, "false_misses": fm,
                                 "wrong_depth": n_off, "flagged": int(np.sum(judged & flagged)),
                                 "wrong_rate": (fh + fm + n_off) / max(int(judged.sum()), 1),
                                 "depth_err_max": float(np.max(dev, initial=0.0)),
                                 "error": ""})
    return pd.DataFrame(rows)


def first_wrong(df: pd.DataFrame) -> pd.DataFrame:
    """Per engine, mesh and family: the largest offset at which the engine first returns a wrong
    answer (scanning from the largest offset down), None where it never does; ``clean_down_to``:
    the smallest offset down to which every answer was right."""
    out = []
    for (eng, mesh, fam), g in df.groupby(["engine", "mesh", "family"], sort=False):
        g = g.sort_values("offset", ascending=False)
        wrong = g[(g["false_hits"].fillna(0) + g["false_misses"].fillna(0) + g["wrong_depth"].fillna(0)) > 0]
        failed = g[g["error"].fillna("") != ""]
        first = float(wrong["offset"].iloc[0]) if len(wrong) else None
        clean = g[g["offset"] > first] if first is not None else g
        out.append({"engine": eng, "mesh": mesh, "family": fam, "first_wrong_offset": first,
                    "clean_down_to": float(clean["offset"].min()) if len(clean) else None,
                    "failed_sets": len(failed)})
    return pd.DataFrame(out)


def summary_table(df: pd.DataFrame) -> pd.DataFrame:
    """Engine × (mesh · family): the offset below which it first returns a wrong answer."""
    fw = first_wrong(df)

    def cell(r):
        if r["failed_sets"]:
            return f"failed on {r['failed_sets']} set(s)"
        return f"δ = {r['first_wrong_offset']:.0e}" if pd.notna(r["first_wrong_offset"]) else \
            f"none down to {df['offset'].min():.0e}"

    fw["cell"] = fw.apply(cell, axis=1)
    fw["where"] = fw["mesh"] + " · " + fw["family"]
    return fw.pivot(index="engine", columns="where", values="cell").reindex(
        index=list(dict.fromkeys(fw["engine"])), columns=list(dict.fromkeys(fw["where"]))).reset_index()


def markdown(df: pd.DataFrame) -> str:
    """The summary table as markdown."""
    return summary_table(df).to_markdown(index=False)


def plot(df: pd.DataFrame, path: Path) -> Path | None:
    """Two rows (wrong hits and misses in % of the judged rays; the largest depth error where both
    hit), one column per ray family, one line per engine over every mesh (rays summed, errors
    maxed), offsets decreasing to the right; written atomically as PNG.  None without rows."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..run.results import write_atomic

    ok = df[df["error"].fillna("") == ""]
    if ok.empty:
        return None
    fams = [f for f in FAMILIES if f in set(ok["family"])]
    engines = list(dict.fromkeys(ok["engine"]))
    fig, axes = plt.subplots(2, len(fams), figsize=(4.6 * len(fams), 7.2), squeeze=False, sharex=True)
    markers = "osD^v<>ph*"
    styles = ["-", "--", "-.", ":"]
    for j, fam in enumerate(fams):
        g = ok[ok["family"] == fam]
        for k, eng in enumerate(engines):
            e = g[g["engine"] == eng].groupby("offset").agg(
                wrong=("false_hits", "sum"), miss=("false_misses", "sum"), off=("wrong_depth", "sum"),
                judged=("judged", "sum"),
                flagged=("flagged", "sum"), err=("depth_err_max", "max")).sort_index(ascending=False)
            if e.empty:
                continue
            # engines that agree exactly would hide each other: a small horizontal shift per engine
            x = e.index.to_numpy() * 10 ** (0.06 * (k - (len(engines) - 1) / 2))
            kw = dict(marker=markers[k % len(markers)], ls=styles[k % len(styles)], label=eng, ms=5, lw=1.4)
            line, = axes[0, j].plot(x, 100.0 * (e["wrong"] + e["miss"] + e["off"]) / e["judged"].clip(lower=1), **kw)
            if e["flagged"].sum() > 0:  # "no answer" (a failure status) is not a wrong answer: drawn apart
                axes[0, j].plot(x, 100.0 * e["flagged"] / e["judged"].clip(lower=1), color=line.get_color(), lw=0.8,
                                ls=":", marker=markers[k % len(markers)], mfc="none", ms=4, label=f"{eng}: flagged")
            axes[1, j].plot(x, np.maximum(e["err"].to_numpy(float), 1e-17), **kw)
        axes[0, j].set_title(f"{fam} rays ({', '.join(dict.fromkeys(g['mesh']))})")
        axes[0, j].set_ylabel("wrong answers [% of judged rays]")
        axes[1, j].set_ylabel("max depth error where both hit")
        axes[1, j].set_yscale("log")
        axes[1, j].axhline(math.sqrt(np.finfo(np.float32).eps), color="0.6", lw=0.8, ls=":")
        axes[1, j].text(0.02, math.sqrt(np.finfo(np.float32).eps) * 1.5, "float32 √ε", color="0.45", fontsize=8,
                        transform=axes[1, j].get_yaxis_transform())
        for i in range(2):
            axes[i, j].set_xscale("log")
            axes[i, j].invert_xaxis()
            axes[i, j].grid(True, which="major", alpha=0.3)
        axes[1, j].set_xlabel("grazing offset δ (× mesh size)")
    axes[0, 0].legend(fontsize=8, loc="upper left")
    fig.suptitle("Engines at the edge: wrong hits and misses (top; hollow dotted: rays flagged with no answer) and "
                 "depth error (bottom; 0 drawn at 1e-17) as rays graze a feature", fontsize=10)
    fig.tight_layout()
    path = Path(path)
    write_atomic(path, lambda tmp: fig.savefig(tmp, format="png", dpi=90))
    plt.close(fig)
    return path


def read(run_dir) -> pd.DataFrame:
    """``run_dir``'s :data:`FILE` as written (``error`` "" where an engine answered)."""
    df = pd.read_csv(Path(run_dir) / FILE, dtype={"error": str}, keep_default_na=False, na_values={
        c: [""] for c in ("false_hits", "false_misses", "wrong_depth", "flagged", "wrong_rate", "depth_err_max",
                         "tolerance")})
    if "error" not in df:
        df["error"] = ""
    return df


def section(run_dir) -> tuple[str, pd.DataFrame, Path] | None:
    """The report's section for a run directory holding :data:`FILE` (``bench edges --out RUN_DIR``):
    ``(note, first-wrong table, plot path)``, which :mod:`bench.report.sections` lays out; None
    without one."""
    path = Path(run_dir) / FILE
    if not path.is_file():
        return None
    df = read(run_dir)
    note = (f"Per engine, mesh and ray family: the largest grazing offset δ (× the mesh's size) at which it first "
            f"returns a wrong answer (a false hit, a false miss, or a hit further than √ε(dtype)·max(1, T) from the "
            f"exact float64 first hit: another surface), scanning δ from "
            f"{df['offset'].max():.0e} down to {df['offset'].min():.0e} ({int(df['rays'].iloc[0])} rays per set, "
            f"half just outside the feature, half just inside; `bench/studies/edges.py`, {PLOT}).")
    return note, summary_table(df), Path(run_dir) / PLOT


__all__ = ["DEFAULT_ENGINES", "DEFAULT_MESHES", "DEFAULT_OFFSETS", "FAMILIES", "check_arguments", "edges_table",
           "engine_callables", "feature_rays", "first_wrong", "markdown", "plot", "section",
           "summary_table", "trimesh_first_hits"]
