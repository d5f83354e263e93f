"""``python -m bench backends``."""

from __future__ import annotations

import argparse


ORDER = 7
HELP = ("list backends and what they can do")


def add_arguments(p: argparse.ArgumentParser) -> None:
    pass


def run(args) -> int:
    from impls import registry

    for bid in registry.default_ids():
        b = registry.resolve(bid)
        if isinstance(b, registry.Unavailable):
            print(f"{bid:12s} unavailable: {b.reason}")
        else:
            caps = b.capabilities
            print(f"{bid:12s} methods={','.join(b.methods())} dtypes={','.join(caps.dtypes)} autodiff={caps.autodiff} jit={caps.jit}")
    return 0

