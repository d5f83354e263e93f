"""``python -m bench edges``."""

from __future__ import annotations

import argparse
from pathlib import Path

from ._common import ProgressLines, error, int_at_least, split

ORDER = 11
HELP = ("per engine, wrong hits/misses and depth error against the grazing offset at mesh edges, vertices and "
        "faces parallel to the ray (bench/studies/edges.py)")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--backend", action="append", help="backends to add to embree, open3d, warp, mitsuba, trimesh, "
                   "trimesh+embreex and numpy (e.g. jax:cpu, warp:cuda): raycast where offered, else --method")
    p.add_argument("--engines", action="append", help="replace the default engines (embree,open3d,warp,mitsuba,trimesh,"
                   "trimesh+embreex,numpy) by these")
    p.add_argument("--method", default="hybrid_secant", help="root finder of the backends without raycast "
                   "(float64, default knobs; default hybrid_secant)")
    p.add_argument("--mesh", default=None, help="stored meshes, comma-separated (default torus,fin,blob)")
    p.add_argument("--family", default=None, help="ray families, comma-separated (default edge,vertex,parallel)")
    p.add_argument("--offsets", default=None, help="grazing offsets × mesh size (default 1e-2,1e-3,…,1e-9)")
    p.add_argument("--rays", type=int_at_least(2), default=64, help="rays per mesh, family and offset (default 64)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", help="write edges.csv and edges.png there; a run directory's report then shows them")
    p.add_argument("--quiet", action="store_true", help="no progress lines")


def _given(value, default) -> list[str]:
    """An option's comma-separated items; an option given empty stays empty (and is refused)."""
    return list(default) if value is None else [v.strip() for v in value.split(",") if v.strip()]


def run(args) -> int:
    """Wrong hits and misses of each engine against the grazing offset (:mod:`bench.studies.edges`).
    Every argument is checked before any ray is cast (one ``error:`` line, exit 2); a line as each
    stage starts and at least every 30 s of it; ``--out`` is locked for the whole command and its
    files (edges.csv, edges.png) written atomically; a run directory's report gains the section."""
    from impls import registry

    from ..run.heartbeat import Heartbeat
    from ..studies import edges

    try:
        meshes, families = _given(args.mesh, edges.DEFAULT_MESHES), _given(args.family, edges.FAMILIES)
        try:
            offsets = [float(x) for x in _given(args.offsets, edges.DEFAULT_OFFSETS)]
        except ValueError:
            raise ValueError(f"--offsets: {args.offsets!r} must be comma-separated numbers, e.g. 1e-2,1e-5,1e-9") from None
        edges.check_arguments(meshes, offsets, families, args.rays)
    except ValueError as exc:
        return error(str(exc))
    for option, given in (("--engines", split(args.engines) or []), ("--backend", split(args.backend) or [])):
        unknown = [b for b in given if b not in (edges.TRIMESH, edges.TRIMESH_EMBREE)
                   and getattr(registry.resolve(b), "unknown", False)]
        if unknown:  # (named by the option that gave them)
            return error(f"{option}: {', '.join(unknown)} name no backend; `python -m bench backends` lists them")
    ids = list(dict.fromkeys((split(args.engines) or list(edges.DEFAULT_ENGINES)) + (split(args.backend) or [])))
    lock = None
    if args.out:
        from ..run.rundir import RunLock, make_dir

        try:
            lock = RunLock(make_dir(Path(args.out))).acquire()
        except ValueError as exc:
            return error(str(exc))
        except OSError as exc:
            return error(f"--out: cannot lock {args.out}: {exc.strerror or exc}; pass a directory you can write")
    engines, notes = edges.engine_callables(ids, method=args.method)
    lines = ProgressLines(periodic=False)
    for line in notes:
        lines.line(line)
    with Heartbeat(None if args.quiet else lines.line) as beat:
        df = edges.edges_table(engines, meshes=meshes, families=families, offsets=offsets, n_rays=args.rays,
                               seed=args.seed, stage=beat.stage)
    print("offset δ (× mesh size) at which each engine first returns a wrong answer (false hit, false miss, or a hit "
          "beyond its dtype's √ε depth tolerance), scanning δ downward:")
    print(edges.markdown(df))
    if args.out:
        from ..run.results import write_atomic

        out = Path(args.out)
        write_atomic(out / edges.FILE, lambda tmp: df.to_csv(tmp, index=False))
        image = edges.plot(df, out / edges.PLOT)
        print(f"wrote {out / edges.FILE}" + (f", {image}" if image else ""))
        if (out / "environment.json").exists():  # a run directory: its report gains the section
            from ..report.build import build_from_dir

            build_from_dir(out)
            print(f"rebuilt {out / 'report.html'}")
        lock.release()
    return 0
