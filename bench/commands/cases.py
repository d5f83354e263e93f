"""``python -m bench cases``."""

from __future__ import annotations

import argparse

from ._common import error, load_user_cases, split

ORDER = 4
HELP = ("list the case catalog")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--case", help="glob on ids")
    p.add_argument("--tag", action="append", help="only cases with these tags")
    p.add_argument("--cases", action="append", help="also list your own cases: package.module:attribute (see run --cases)")


def run(args) -> int:
    from reference import catalog

    err = load_user_cases(args)
    if err:
        return error(err)

    tags = set(split(args.tag) or [])
    try:
        found = catalog(args.case, tags)
    except ValueError as exc:
        return error(f"--case/--tag: {exc}")
    if not found:
        known = sorted({t for c in catalog() for t in c.tags})
        what = " and ".join(x for x in (f"--case {args.case!r}" if args.case else "",
                                         f"--tag {','.join(sorted(tags))}" if tags else "") if x) or "the catalog"
        return error(f"{what}: no case matches; known tags: {', '.join(known)} (`python -m bench cases` lists all)")
    for c in found:
        print(f"{c.id:40s} v{c.version}  rays={c.n_rays:<6d} tags={','.join(c.tags)}  {c.description}")
    return 0

