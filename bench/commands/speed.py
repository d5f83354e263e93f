"""``python -m bench speed``."""

from __future__ import annotations

import argparse

from ._common import ALLOCATOR_HELP, error, int_at_least, json_dict, split, write_out_file

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
    args.side_given = args.side is not None
    if args.side is None:
        args.side = 1024
    environment.configure_threads(args.threads)
    allocator = environment.tune_allocator() if args.allocator == "tuned" else "default"
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
