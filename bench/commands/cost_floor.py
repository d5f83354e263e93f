"""``python -m bench cost-floor``."""

from __future__ import annotations

import argparse

from ._common import error, int_at_least, json_dict, write_out_file

ORDER = 9
HELP = ("the fewest φ evaluations per ray any Lipschitz-certified root finder could spend on bench "
        "speed's two scenes (an oracle's greedy sphere cover), beside a method's (bench/studies/cost_floor.py)")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--backend", default="numpy", help="backend whose method is set beside the floor (default numpy)")
    p.add_argument("--method", default="hybrid_secant", help="a certified root finder (default hybrid_secant)")
    p.add_argument("--knobs", type=json_dict, help="JSON knob dict (default: the method's defaults)")
    p.add_argument("--side", type=int_at_least(1), default=256, help="rays per image side (default 256)")
    p.add_argument("--out", help="write the rows as JSON")


def run(args) -> int:
    import numpy as np

    from impls import METHODS, registry

    from ..studies import cost_floor, speed

    spec = METHODS.get(args.method)
    if spec is None or spec.family != "root" or "min_step" not in {k.name for k in spec.knobs}:
        certified = sorted(m for m, s in METHODS.items() if s.family == "root" and "min_step" in {k.name for k in s.knobs})
        return error(f"--method {args.method!r} is not a certified marching root finder; choose one of {certified}")
    try:
        backend = registry.resolve(args.backend)
    except Exception as exc:  # an unknown or unavailable backend: one line naming it
        return error(f"--backend {args.backend!r}: {exc}")
    try:
        knobs = spec.validate(args.knobs or {})
    except ValueError as exc:
        return error(f"--knobs: {exc}")
    floors, evals = {}, {}
    for name, (scene, o, d) in speed.scenes(args.side).items():
        p = backend.prepare(args.method, scene, o, d, t_min=0.0, t_max=10.0, **(args.knobs or {}))
        evals[name] = np.asarray(p.result(p.run()).evals)
        floors[name] = cost_floor.floor_per_ray(scene, o, d, 10.0, knobs["min_step"])
    rows = cost_floor.table(evals, floors)
    for r in rows:
        print(f"{r['scene']:10s} {r['rays']} rays: floor {r['floor_per_ray']:.2f} evaluations per ray "
              f"({r['floor_per_hit']:.2f} per hit), {args.method} · {backend.id} {r['evals_per_ray']:.2f} "
              f"({r['evals_per_hit']:.2f} per hit), min_step {knobs['min_step']:g}")
    if args.out:
        from ..run.results import write_json

        err = write_out_file(args.out, lambda path: write_json(path, rows))
        if err:
            return error(err)
    return 0
