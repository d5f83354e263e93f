"""The plan of a run: which configurations (case × backend × dtype × method × knobs), in which
order (:func:`plan`), from a suite and the options that narrow it."""

from __future__ import annotations

import dataclasses
import datetime as _dt
import fnmatch
import secrets
from pathlib import Path

from impls import METHODS
from reference import Case, catalog
from reference.cases import LARGE

from . import interrupts
from .metrics import family_skip_reason
from .references import load_numerical_hits
from .results import knob_string
from .suites import Suite
from .timing import Timeout, time_limit

#: columns that identify a configuration (a row is a configuration × quantity)
CONFIG_KEY = ["case_id", "backend", "dtype", "method", "knob"]

@dataclasses.dataclass(frozen=True)
class Config:
    case: Case
    backend_id: str
    method: str
    dtype: str
    knobs: dict

    @property
    def key(self) -> tuple[str, str, str, str, str]:
        return (self.case.id, self.backend_id, self.dtype, self.method, knob_string(self.knobs))


def new_run_id() -> str:
    return _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%SZ") + "-" + secrets.token_hex(3)


def select_cases(suite: Suite, case_pattern: str | None) -> list[Case]:
    """``--case`` globs replace the suite's selection; otherwise the suite's glob and tags."""
    if case_pattern:
        return catalog(case_pattern)
    return catalog(suite.case_pattern, set(suite.case_tags) or None)


def method_names(methods: list[str] | None) -> list[str] | None:
    """The catalog's methods that ``--method`` names (names or globs such as ``volume_*``, as
    ``--case`` takes), in catalog order; None when not given.  A name or glob that matches nothing
    is a ValueError naming it (checked by ``bench run`` before it claims its ``--out``, too)."""
    if not methods:
        return None
    unknown = [m for m in methods if not any(fnmatch.fnmatchcase(n, m) for n in METHODS)]
    if unknown:
        raise ValueError(f"--method: unknown method(s) {unknown}; known: {sorted(METHODS)}")
    return [n for n in METHODS if any(fnmatch.fnmatchcase(n, m) for m in methods)]


def check_dtypes(dtypes: list[str] | None) -> None:
    """A ValueError naming the first of ``--dtype``'s that is no dtype a backend may run."""
    for dt in dtypes or ():
        if dt not in ("float64", "float32", "float16", "bfloat16"):
            raise ValueError(f"--dtype: unknown dtype {dt!r}; use float64 and/or float32 (float16 and bfloat16 run on "
                             "a plug-in backend that lists them in its capabilities.dtypes; the built-in ones skip them)")


#: user cases whose reference answers could not be computed within the limit, in this process:
#: (case id, case version) → the reason (so that every configuration of the case is skipped with
#: it at once, not after the limit again)
_GAVE_UP: dict[tuple[str, str], str] = {}


#: the run directory's in-flight note (:data:`bench.run.supervise.INFLIGHT`) while :func:`plan` runs
#: in a run (:func:`planning_in`), else None: a user case's field that ends the process while its
#: reference answers are computed (``os._exit``, an abort in native code) leaves it naming the
#: case, so that the supervisor resumes the run and the resumed plan skips that case
#: (:func:`planning_deaths`).  Before, such a field ended ``bench run`` with its own exit status,
#: no rows and nothing to resume.
_PLANNING_NOTE: list[Path | None] = [None]


class planning_in:
    """``with planning_in(out_dir, died):`` around :func:`plan` in a run: user cases' reference work
    leaves a note in ``out_dir`` while it runs, and the cases of ``died`` (:func:`planning_deaths`:
    their field ended an earlier session's process) are skipped with their reason, from here to
    the next run this process starts (its entry replaces them)."""

    def __init__(self, out_dir: Path | None, died: dict[str, str] | None = None):
        from .supervise import INFLIGHT

        self.path = None if out_dir is None else Path(out_dir) / INFLIGHT
        self.died = dict(died or {})

    def __enter__(self):
        _PLANNING_NOTE[0] = self.path
        _DIED.clear()
        _DIED.update(self.died)
        return self

    def __exit__(self, *exc):
        _PLANNING_NOTE[0] = None  # (the cases of ``died`` stay skipped for the run's configurations)
        return False


def planning_deaths(out_dir: Path, env: dict) -> dict[str, str]:
    """The user cases whose field ended an earlier session's process at planning: the run's record
    (``env["planning_deaths"]``, JSON {"case id version": reason}) plus the one the in-flight note names (its
    note removed, the record updated in ``env``), for :class:`planning_in` to skip."""
    import json

    from .supervise import INFLIGHT, read_note

    died = json.loads(env.get("planning_deaths") or "{}")
    note = read_note(Path(out_dir) / INFLIGHT)
    if note and note.get("planning"):
        died[f"{note['planning']} {note.get('version', '')}"] = (
            f"planning: the field of {note['planning']} ended the process ({note.get('status', 'its exit')}) while its "
            "reference answers (the numerical first hits) were computed: os._exit, an abort or a crash in its code; "
            "its rows are skipped, the rest of the run went on. Call the field on a few points yourself to see it")
        (Path(out_dir) / INFLIGHT).unlink(missing_ok=True)
        env["planning_deaths"] = json.dumps(died, sort_keys=True)
    return died


#: "case id version" → reason, of the user cases whose field ended a process at planning, while
#: :class:`planning_in` is in force (:func:`planning_deaths`; an edited field is another version, and runs)
_DIED: dict[str, str] = {}


def _user_key(case) -> tuple[bool, tuple[str, str]]:
    return "user" in getattr(case, "tags", ()), (case.id, getattr(case, "version", ""))


def _user_limit(case, limit_s: float | None) -> float | None:
    """The limit on a user case's reference answers: ``limit_s`` per pass of the numerical
    reference (:data:`reference.numerical.CHUNK_RAYS` rays), so that it bounds a hang, not the
    size of the case (a 1024² user camera, 256 passes, takes minutes where 64 rays take
    milliseconds)."""
    from reference.numerical import CHUNK_RAYS

    if not limit_s:
        return None
    return float(limit_s) * max(1, -(-int(getattr(case, "n_rays", 1)) // CHUNK_RAYS))


def _bounded(case, limit_s: float | None, fn):
    """``(fn(), None)``, or ``(None, reason)`` where ``fn`` (work that runs a user case's field)
    raised, exited or, for a user's case, ran past :func:`_user_limit`; a timeout is remembered as
    the case's reason for the rest of the process."""
    user, key = _user_key(case)
    if user and key in _GAVE_UP:
        return None, _GAVE_UP[key]
    if user and f"{key[0]} {key[1]}" in _DIED:
        return None, _DIED[f"{key[0]} {key[1]}"]
    note = _PLANNING_NOTE[0] if user else None
    try:
        if note is not None:  # (the supervisor resumes the run if the field ends the process here)
            import os
            import time

            from .results import write_json

            write_json(note, {"planning": case.id, "version": key[1], "key": ["planning", case.id], "pid": os.getpid(),
                              "what": f"planning {case.id} (its field's reference answers)",
                              "started": time.time(), "limit_s": 0.0})
        with time_limit(_user_limit(case, limit_s) if user else None, "--reference-timeout"):
            return fn(), None
    except Timeout as exc:
        if not user:  # (an outer limit's)
            raise
        _GAVE_UP[key] = reason = (f"planning: the reference answers of {case.id} (its field's numerical first hits) "
                                  f"{exc}; raise --reference-timeout if the field is slow, not stuck")
        return None, reason
    except BaseException as exc:  # a reference that cannot answer is a reason, not a crash
        if not interrupts.is_fault(exc):
            raise
        return None, f"planning: {type(exc).__name__}: {exc}"
    finally:
        if note is not None:
            note.unlink(missing_ok=True)


def applies(spec, case, limit_s: float | None = None) -> str | None:
    """Why ``spec`` cannot run on ``case`` whatever the backend (scene requirements, missing
    reference answers), or None.  A user's case (tag ``user``) runs the user's field to get its
    reference answers (the numerical first hits): that is bounded by ``limit_s``
    (``--reference-timeout``; None or 0: none) per pass of the reference (:func:`_user_limit`),
    and a field that raises, calls ``sys.exit`` or hangs past it is a reason for that case's
    rows, not the end of the run.  (Unbounded, a user
    field sleeping in ``fn`` held a run in planning past its --timeout and --reference-timeout;
    ``sys.exit(3)`` in one ended the run with exit code 3 and no rows.)  The catalog's own
    references are trusted code and not limited: on a loaded machine a cold mesh reference may
    take longer than any such limit sized to an idle one."""
    reason, failed = _bounded(case, limit_s, lambda: spec.skip_reason(case.scene) or family_skip_reason(spec, case))
    return failed or reason


def plan(suite: Suite, backend_ids: list[str], case_pattern: str | None, methods: list[str] | None,
         dtypes: list[str] | None, reference_disk: Path | None = None,
         reference_timeout_s: float | None = None) -> list[Config]:
    """Configurations in measuring order.

    Per method: the cases it applies to (at most ``suite.max_cases``, all when ``--case`` is
    given; fewest rays first with ``suite.small_cases_first``, one per scene family in turn with
    ``suite.diverse_cases``), its knob sweep on the first ``suite.sweep_cases`` of them and its
    default knobs on the rest (plus, beyond ``max_cases``, every applicable case matching
    the method's ``suite.always_cases``, at default knobs; secondary dtypes: see ``Suite.secondary_dtype_cases``;
    never the suite's ``exclude_cases`` for it, unless ``--case`` names cases other than by the
    match-all ``*``); a case it does not apply to gets one configuration (default knobs), which the
    runner records as skipped with the reason.  Order: every default-knob configuration first
    (so a time budget cuts sweep points, not coverage), then the sweep points; within each,
    case by case, knobs outer and backends inner, rotated by one at every knob, so backends
    interleave in time and none is always first.  ``reference_disk``: where numerical first hits
    are kept between runs (:func:`bench.run.references.load_numerical_hits`); ``reference_timeout_s``:
    the limit on a user case's reference answers (:func:`applies`)."""
    methods = method_names(methods)
    names = [m for m in (suite.methods or tuple(METHODS)) if not methods or m in methods]
    check_dtypes(dtypes)
    cases = select_cases(suite, case_pattern)
    for case in cases:  # numerical first hits from the cache directory, where it has them
        # (a failure here is said where the answer is read: applies)
        _bounded(case, reference_timeout_s, lambda: load_numerical_hits(case, reference_disk))
    explicit = bool(case_pattern)
    # the suite's cost exclusions hold for the match-all sweep, not for cases named on purpose
    names_cases = explicit and any(g.strip() not in ("", "*") for g in str(case_pattern).split(","))
    if suite.small_cases_first and not explicit:
        cases = sorted(cases, key=lambda c: c.n_rays)  # stable: catalog order among equals
    order = {c.id: i for i, c in enumerate(cases)}
    # (stage, case index, case, method, knob index, knobs, rank among the method's applicable cases)
    work: list[tuple[int, int, Case, str, int, dict, int]] = []
    for method in names:
        spec = METHODS[method]
        sweep = suite.sweep_for(spec)
        usable = []
        excluded = () if names_cases else (*suite.exclude_cases.get(spec.family, ()),
                                             *suite.exclude_cases.get(spec.name, ()))
        for case in cases:
            if any(fnmatch.fnmatchcase(case.id, g) for g in excluded):
                continue
            if applies(spec, case, reference_timeout_s) is not None:
                work.append((0, order[case.id], case, method, 0, sweep[0], 0))
            else:
                usable.append(case)
        if suite.diverse_cases and not explicit:
            lead = suite.lead_cases.get(spec.family, suite.lead_cases.get("*", ()))
            usable = _one_per_family(usable, lead, shift=names.index(method) if suite.rotate_families else 0)
        if not explicit and suite.max_cases is not None:
            globs = suite.always_cases.get(spec.name, suite.always_cases.get(spec.family, ()))
            extra = [c for c in usable[suite.max_cases:] if any(fnmatch.fnmatchcase(c.id, g) for g in globs)]
            usable = usable[:suite.max_cases] + extra
        for rank, case in enumerate(usable):
            swept = explicit or suite.sweep_cases is None or rank < suite.sweep_cases
            for k, knobs in enumerate(sweep if swept else sweep[:1]):
                work.append((0 if k == 0 else 1, order[case.id], case, method, k, knobs, rank))
        if not explicit:
            for case in _scale_cases(suite, spec):
                order.setdefault(case.id, len(order))
                # rank past every secondary-dtype case: the suite's first dtype only
                work.append((0, order[case.id], case, method, 0, sweep[0], len(usable) + len(cases)))
    work.sort(key=lambda w: (w[0], w[1]))  # stable: method order, then knob order, kept
    all_dtypes = list(dtypes or suite.dtypes)
    cfgs = []
    for _, _, case, method, k, knobs, rank in work:
        for i, dtype in enumerate(method_dtypes(METHODS[method], all_dtypes, explicit=bool(dtypes))):
            if i > 0 and not dtypes and suite.secondary_dtype_cases is not None and (
                    k > 0 or rank >= suite.secondary_dtype_cases):
                continue  # secondary dtypes: defaults on the first cases only (see Suite)
            r = k % max(len(backend_ids), 1)
            for bid in backend_ids[r:] + backend_ids[:r]:
                cfgs.append(Config(case, bid, method, dtype, dict(knobs)))
    return cfgs


def _scale_cases(suite: Suite, spec) -> list[Case]:
    """The cameras at scale ``suite.scale_cases`` names for ``spec`` (its name, else its family)
    whose scene meets its requirements, in catalog order.  Only the scene's requirements are
    checked here, not :func:`applies`' reference answers: those cost minutes at 1024² and are
    computed once, by the run (a camera without them becomes a skipped row with the reason)."""
    globs = suite.scale_cases.get(spec.name, suite.scale_cases.get(spec.family, ()))
    if not globs:
        return []
    return [c for c in catalog(",".join(globs), {LARGE}) if spec.skip_reason(c.scene) is None]


def _family(case) -> str:
    return case.id.split(".", 1)[0]


def _one_per_family(cases: list, lead: tuple[str, ...] = (), shift: int = 0) -> list:
    """``cases`` reordered: those of ``lead`` in ``cases`` (in that order; the first is where the
    sweep runs), then round-robin over the other scene families (first case of each, then
    second…), the families rotated by ``shift`` so that different methods cover different
    families."""
    first = [c for lid in lead for c in cases if c.id == lid]
    by_family: dict[str, list] = {}
    for c in cases:
        if c not in first:
            by_family.setdefault(_family(c), []).append(c)
    lead_families = {_family(c) for c in first}
    others = [g for f, g in by_family.items() if f not in lead_families]
    k = shift % len(others) if others else 0
    # lead families come last, so the cases after the lead ones are of other families
    groups = others[k:] + others[:k] + [g for f, g in by_family.items() if f in lead_families]
    out, depth = list(first), 0
    while len(out) < len(cases):
        out += [g[depth] for g in groups if depth < len(g)]
        depth += 1
    return out


def method_dtypes(spec, run_dtypes: list[str], explicit: bool) -> list[str]:
    """The dtypes ``spec`` is planned in: the run's, or for a method that computes in its own
    (``MethodSpec.dtypes``, an engine's ``raycast``) those, narrowed to the ones ``--dtype`` names
    (``explicit``) when it names any of them (when it names none, the run's dtypes: the rows are
    skipped with the reason, not left out)."""
    own = getattr(spec, "dtypes", None)
    if not own:
        return list(run_dtypes)
    if explicit:
        return [d for d in run_dtypes if d in own] or list(run_dtypes)
    return list(own)
