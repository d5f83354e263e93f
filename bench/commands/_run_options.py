"""``bench run`` options that define a run's plan: recorded in environment.json, restored by
``--resume``, and checked for emptiness and contradictions before anything runs."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from ._common import split

#: ``bench run`` options that define a run's plan and how its rows are measured: recorded in
#: environment.json (``run_options``) and restored by ``--resume``, so a resumed run finishes the
#: plan it started, its stages (claims, stability) included (``--case '*'`` stays the catalog sweep without retyping it).  The timing-sample
#: options (--min-time, --min-repeats, --max-time, --timeout, --rounds), --budget, --cluster and
#: --scheduler are per session: a resume may change them, as the budget hint says.
RESUMED_OPTIONS = ("suite", "case", "method", "dtype", "backend", "cases", "threads", "allocator", "accuracy_only",
                   "no_claims", "no_stability")


def flag(dest: str) -> str:
    return "--" + dest.replace("_", "-")


def shown(dest: str, value) -> str:
    """An option as the user would type it: ``--case 'box.*'``, ``--dtype 'float32,float64'``, ``no --case``."""
    if value is None or value is False:
        return "no " + flag(dest)
    if value is True:
        return flag(dest)
    return f"{flag(dest)} {','.join(value) if isinstance(value, list) else value!r}"


def restore_run_options(args) -> str | None:
    """With ``--resume``: set ``args``' :data:`RESUMED_OPTIONS` to those recorded by the run in
    ``--out``; an option given now that differs from the recorded one (and from its default) is an
    error naming it, not a silently different plan.  A run recorded before options were (no
    ``run_options``) resumes with the options given now, with a warning.  Returns an error message
    or None."""
    env_path = Path(args.out) / "environment.json"
    try:
        recorded = json.loads(json.loads(env_path.read_text()).get("run_options", "null"))
    except (OSError, ValueError):
        return None  # the runner reports a missing or broken environment.json with the fix
    if recorded is None:
        print(f"warning: {env_path} records no run options (a run from an older isobench): resuming with the "
              "--suite/--case/--method/--dtype/--backend given now; give the ones it started with",
              file=sys.stderr, flush=True)
        return None
    defaults = args.run_option_defaults
    for dest in RESUMED_OPTIONS:
        given, then = normal(dest, getattr(args, dest)), normal(dest, recorded.get(dest, defaults[dest]))
        if given != normal(dest, defaults[dest]) and given != then:
            return (f"{flag(dest)}: the run in {args.out} was started with {shown(dest, then)} "
                    f"(given now: {shown(dest, given)}); "
                    f"--resume finishes the plan it started: drop {flag(dest)} (the recorded value is used), "
                    "or start a new run with another --out")
        setattr(args, dest, then)
    return None


def normal(dest: str, value):
    """Repeated and comma-separated list options as one list (``--dtype a,b`` = ``--dtype a --dtype b``)."""
    return split(value) if dest in ("method", "dtype", "backend", "cases") else value


def run_options(args, backend_ids) -> str:
    """The JSON of :data:`RESUMED_OPTIONS` as this run uses them (``backend_ids``: the backends as
    given, a plug-in by its spec, so that a resume resolves them again)."""
    rec = {dest: normal(dest, getattr(args, dest)) for dest in RESUMED_OPTIONS}
    rec["backend"] = list(backend_ids)
    return json.dumps(rec, sort_keys=True)


#: ``bench run`` options given as lists or globs: given, they must name something
LIST_OPTIONS = ("case", "method", "dtype", "backend", "cases", "rerun_case")


def empty_option(args, dests) -> str | None:
    """An error for the first of ``dests`` given but empty (``--method ''`` would otherwise mean
    "all"), or None."""
    for dest in dests:
        value = getattr(args, dest, None)
        if value is None:
            continue
        items = split(value) if isinstance(value, list) else [v for v in str(value).split(",") if v.strip()]
        if not items:
            shown = ",".join(value) if isinstance(value, list) else value
            return (f"{flag(dest)}: given empty ({shown!r}); name what you mean (`python -m bench cases` / "
                    f"`backends` list them), or leave {flag(dest)} out for the default")
    return None


def contradictions(args) -> str | None:
    """An error naming two ``bench run`` options that cannot both hold, or None."""
    if args.min_time is not None and args.max_time is not None and args.min_time > args.max_time:
        return (f"--min-time {args.min_time:g} and --max-time {args.max_time:g}: at least {args.min_time:g} s of "
                f"timed calls cannot fit in at most {args.max_time:g} s; give --min-time ≤ --max-time")
    if args.rounds > 1 and args.accuracy_only:
        return (f"--rounds {args.rounds} and --accuracy-only: an accuracy-only run takes no timing samples to pool "
                "over rounds; drop one")
    if args.rerun_case and not args.resume:
        return "--rerun-case without --resume: a new run runs every case anyway; add --resume --out DIR, or drop it"
    return None

