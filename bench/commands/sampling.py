"""``python -m bench sampling``."""

from __future__ import annotations

import argparse
from pathlib import Path

from ._common import ProgressLines, error, int_at_least

ORDER = 10
HELP = ("samples per ray each volume sampler needs to reach colour error targets "
       "against the rendering integral (bench/studies/sampling.py)")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--case", help="case ids, comma-separated (default: sphere.camera.64x64,torus.camera.32x32)")
    p.add_argument("--targets", help="colour error targets, comma-separated (default 1e-2,1e-3,1e-4)")
    p.add_argument("--density", default="nerf", choices=("nerf", "volsdf", "neus"), help="density model (default nerf)")
    p.add_argument("--sharpness", type=float, default=50.0, help="density sharpness s, finite and > 0 (default 50)")
    p.add_argument("--max-rays", type=int_at_least(1), default=64, help="reference rays per case (default 64)")
    p.add_argument("--n-max", type=int_at_least(4), default=4096, help="largest N searched (default 4096)")
    p.add_argument("--out", help="write sampling.csv there; a run directory's report then shows the table")
    p.add_argument("--quiet", action="store_true", help="no progress lines")


def run(args) -> int:
    """Samples per volume sampler to colour error targets (:mod:`bench.studies.sampling`).  Every argument
    is checked before the costly reference integrals (one ``error:`` line, exit 2); progress lines
    come as each stage starts and at least every 30 s of it; ``--out`` is locked (a run directory
    has one writer) for the whole command."""
    from ..studies import sampling
    from ..run.environment import ROOT
    from ..run.references import NotApplicable

    cases = [c.strip() for c in args.case.split(",") if c.strip()] if args.case is not None \
        else list(sampling.DEFAULT_CASES)
    try:
        targets = (tuple(float(t) for t in args.targets.split(",") if t.strip()) if args.targets is not None
                   else sampling.DEFAULT_TARGETS)
    except ValueError:
        return error(f"--targets: {args.targets!r} must be comma-separated numbers, e.g. 1e-2,1e-3")
    try:
        sampling.check_arguments(cases, targets, args.sharpness)
    except ValueError as exc:
        return error(str(exc))
    lock = None
    if args.out:
        from ..run.rundir import RunLock, make_dir

        try:  # before minutes of work: a path that cannot be written, or a run directory being written
            lock = RunLock(make_dir(Path(args.out))).acquire()
        except ValueError as exc:
            return error(str(exc))
        except OSError as exc:
            return error(f"--out: cannot lock {args.out}: {exc.strerror or exc}; pass a directory you can write")
    lines = ProgressLines(periodic=False)
    try:
        df = sampling.sampling_table(cases, targets, density=args.density, sharpness=args.sharpness,
                                     max_rays=args.max_rays, n_max=args.n_max, disk=ROOT / "reports" / ".refcache",
                                     progress=None if args.quiet else lines.line)
    except NotApplicable as exc:  # e.g. a density model with no continuous integral at these settings
        return error(f"--case/--density/--sharpness: no rendering integral to sample towards: {exc}")
    print(sampling.markdown(df))
    if args.out:
        from ..run.results import write_atomic

        out = Path(args.out)
        write_atomic(out / sampling.FILE, lambda tmp: df.to_csv(tmp, index=False))
        print(f"wrote {out / sampling.FILE}")
        if (out / "environment.json").exists():  # a run directory: its report gains the section
            from ..report.build import build_from_dir

            build_from_dir(out)
            print(f"rebuilt {out / 'report.html'}")
        lock.release()
    return 0

