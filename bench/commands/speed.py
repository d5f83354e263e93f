"""``python -m bench speed``."""

from __future__ import annotations

import argparse

from ._common import ALLOCATOR_HELP, ProgressLines, error, int_at_least, json_dict, split, write_out_file

ORDER = 9
HELP = ("root finders on 2^20 rays at a sphere and a torus ∪ box, in units of the "
       "closed-form sphere intersection, against their speed targets (bench/studies/speed.py)")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--backend", action="append", help="backend ids (default: all available)")
    p.add_argument("--method", default="hybrid_secant")
    p.add_argument("--knobs", type=json_dict, help='JSON knob dict, e.g. \'{"xtol": 1e-8}\' (default: the method\'s defaults)')
    p.add_argument("--side", type=int_at_least(1), default=None, help="rays per image side (default 1024: 2^20 rays; "
                    "256 with --volume: 2^16 rays)")
    p.add_argument("--no-peers", action="store_true", help="leave out the peers' rows (bench/studies/peers.py: a numba per-ray "
                    "sphere tracer, scipy's Chandrupatla refiner)")
    p.add_argument("--volume", action="store_true", help="volume rendering instead: each backend's volume_nerf_uniform "
                    "against the plain compositing compiled by torch.compile and jax.jit (bench/studies/peers.py)")
    p.add_argument("--mesh", action="store_true", help="the three mesh cameras instead: engines (raycast, float32) and "
                   "--method (float64) side by side, default backends numpy,embree,open3d,warp,mitsuba (bench/studies/speed_mesh.py)")
    p.add_argument("--samples", type=int_at_least(1), default=256, help="samples per ray with --volume (default 256)")
    p.add_argument("--repeats", type=int_at_least(1), default=3)
    p.add_argument("--threads", type=int_at_least(1), default=1, help="threads per library and worker threads of the numpy/torch "
                    "root-finder drivers (default 1)")
    p.add_argument("--allocator", choices=("tuned", "default"), default="tuned", help=ALLOCATOR_HELP)
    p.add_argument("--out", help="write the rows as JSON")


def run(args) -> int:
    from ..run import environment
    from ..studies import peers, speed
    from impls import METHODS, registry

    if args.method not in METHODS or METHODS[args.method].family != "root":
        roots = sorted(m for m, s in METHODS.items() if s.family == "root")
        return error(f"--method: {args.method!r} is not a root finder; choose one of {roots}")
    try:
        METHODS[args.method].validate(dict(args.knobs or {}))
    except (ValueError, TypeError) as exc:
        return error(f"--knobs: {exc}")
    if args.method == "raycast" and not args.mesh:
        return error("--method raycast: an engine's query on meshes; time it with --mesh (the engines answer "
                     "raycast there whatever --method says)")
    args.side_given = args.side is not None
    if args.side is None:
        args.side = 1024
    environment.configure_threads(args.threads)
    allocator = environment.tune_allocator() if args.allocator == "tuned" else "default"
    if args.mesh:
        if args.volume:
            return error("--mesh and --volume: choose one (mesh cameras are timed on root finders and engines)")
        return _speed_mesh(args, allocator)
    ids = split(args.backend) if args.backend else [b.id for b in registry.available()[0]]
    bad = [(bid, b) for bid, b in ((bid, registry.resolve(bid)) for bid in ids) if isinstance(b, registry.Unavailable)]
    if bad:
        return error("--backend: " + "; ".join(f"{bid}: {b.reason}" for bid, b in bad))
    if args.volume:
        side = args.side if args.side_given else 256
        rows, notes = peers.volume_rows(ids, speed.scenes(side), n_samples=args.samples, repeats=args.repeats)
        head = [f"volume rendering, {side}² rays × {args.samples} samples, NeRF density s = 50, no early termination, "
                f"{args.threads} thread(s); time: median (min–max) of {args.repeats}, compile and first call apart"]
        return _report(args, allocator, rows, head, peers.format_volume(rows), notes)
    notes: list[str] = []
    rows = speed.measure(ids, n_side=args.side, method=args.method, repeats=args.repeats, knobs=args.knobs or {},
                         threads=args.threads, peers=not args.no_peers, notes=notes)
    head = [f"{args.side}² rays, {args.method}, {args.threads} thread(s) per library and root-finder driver, "
            f"allocator: {allocator}; × unit = time / numpy closed-form sphere hit of the same rays (same run, 1 thread)"]
    if not args.no_peers:
        head.append("peers (bench/studies/peers.py): peer:numba-st = numba per-ray sphere tracer (hit when φ < 1e-9, "
                    "bounding-sphere clip); peer:scipy = hybrid_secant's march on numpy + scipy find_root "
                    "(hybrid_chandrupatla)")
    return _report(args, allocator, rows, head, speed.format_rows(rows), notes)


def _report(args, allocator: str, rows: list[dict], head: list[str], table: str, notes: list[str]) -> int:
    """Print the rows (with the run's threads and allocator) and write them to ``--out``."""
    from ..run.results import write_json

    for row in rows:
        row["threads"] = args.threads
        row["allocator"] = allocator
    for line in [*head, table, *notes]:
        print(line)
    if args.out:
        err = write_out_file(args.out, lambda path: write_json(path, rows))
        if err:
            return error(err)
    return 0


def _speed_mesh(args, allocator: str) -> int:
    """``speed --mesh`` (:mod:`bench.studies.speed_mesh`): engines (raycast, float32) and root
    finders (``--method``, float64) on the three mesh cameras; default backends numpy, embree,
    open3d (an unavailable one is a line, not an error: its engine is not installed here)."""
    from impls import registry

    from ..run.heartbeat import Heartbeat
    from ..studies import speed_mesh

    ids = split(args.backend) or list(speed_mesh.DEFAULT_BACKENDS)
    unknown = [bid for bid in ids if getattr(registry.resolve(bid), "unknown", False)]
    if unknown:
        return error(f"--backend: {', '.join(unknown)} name no backend; `python -m bench backends` lists them")
    if args.knobs:
        return error("--knobs: not with --mesh (each method runs at its default knobs there)")
    notes: list[str] = []
    lines = ProgressLines(periodic=False)
    with Heartbeat(lines.line) as beat:
        rows = speed_mesh.measure(ids, n_side=args.side, method=args.method, repeats=args.repeats,
                                  peers=not args.no_peers, notes=notes, progress=beat.stage)
    head = [f"mesh cameras, {args.side}² rays, {args.threads} thread(s); raycast (float32) where a backend offers it, "
            f"else {args.method} (float64, default knobs); × unit = time / numpy closed-form sphere hit of the same rays"]
    notes = ["versions: " + speed_mesh.versions_line(rows), *notes]
    return _report(args, allocator, rows, head, speed_mesh.format_rows(rows), notes)
