"""The jax loop driver, jit-compatible.

Fixed shapes, masked updates, compaction by levels (:func:`run_loop`): ``lax.map`` runs the
rays in chunks of ``CHUNK``; within a chunk every stage of the algorithm is a
``lax.while_loop`` over a batch whose rays not in that stage (or finished) keep their values
(``jnp.where`` on the status), and the batch shrinks by ``RATIO`` from level to level as rays
finish (the rays still iterating are gathered with ``jnp.nonzero(size=…)``, a static size);
each chunk's last level stops after ``TAIL_CAP`` steps and the stragglers of all chunks are
finished together.  The levels compact the stages that search for a crossing; a root finder's
refinement and certification stages run on the whole chunk after them (``PARK``).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from jax import lax

from ..core import rootfind
from ..core.driver import _whole_at_least


# Measured (bench/studies/speed.py, torus ∪ box, 2^20 rays, hybrid_secant): a masked step costs about
# 7-9 ns per ray on a 2^16-ray batch, about 30 ns on a 2^20-ray one (the state no longer stays
# in cache) and about 25 ns on 64 rays, so chunks of 2^16.  Batches shrink 4× per level: every
# level is a copy of every stage's loop with φ inlined, so XLA's compile time grows with the
# number of levels, and a harness run compiles once per configuration and times a few calls.
# Ratio 4 against 2 halves the compile at a run time between −17 % and +9 % (measurements:
# CHANGELOG.md, "jax compaction levels").  The last level of a chunk stops after TAIL_CAP steps and hands its
# stragglers to one pass over all chunks' stragglers, so the long tail's loop runs once, not
# once per chunk (0.30 s → 0.25 s in one side-by-side run).
CHUNK = 1 << 16
RATIO = 4
LAST = 64
TAIL_CAP = 128
# The smallest level of a constant-step march (the march_* methods), whose rays take at most
# (t_max − t_min)/step steps: no heavy tail for a 64-row level to serve.  Measured side by side
# on the quick suite's 1,024- and 256-ray cases (docs/performance.md): 256 against 64, compile
# CPU −29 %, run ×0.86–1.07; the certified methods keep LAST (at 256, ×1.25–1.89 slower).
LAST_CONSTANT = 256
# Ladder steps (impls.core.rootfind.MarchRefine.step_ladder) where the knob leaves the choice to
# the driver: none.  The masked levels already run the stragglers in small batches, and there a
# ladder iteration's K samples per row cost more than the loop steps they save: torus ∪ box,
# 2^20 rays, 0.23 s without, 0.27–0.28 s with 16-sample ladders after 64 steps (0.25 s with
# the stage present and never entered).
LADDER = 0
# Ray counts padded to a power of two of at least PAD rows (MaskedSettings.pad): every distinct
# array shape is a compilation of its own (~1-2 s per level on 2 cores), and the tests alone run
# each method on ray sets of 1 to 4,000 rays.  Measured on the jax tests' calls (478, tests -k jax):
# exact shapes 389 distinct kernel keys, powers of two ≥ 64 344; on the conformance suite (then one
# file, tests/test_conformance.py) and tests/test_rootfind_certified.py (-k jax, empty cache) XLA
# compiled 265 → 235 s.  A power of two pads at most 2× (a padding row costs what ray 0 costs).
PAD = 64
# The levels compact only the stages that search for a crossing; a root finder's refinement and
# certification stages run once on the whole chunk after them (run_loop).  Each level is a copy of
# the loops of the stages it runs, and XLA:CPU's compile time grows with them; a bracket's
# refinement takes a few dozen steps on every ray that crossed, no heavy tail for a small level
# to serve.  Measured side by side (docs/performance.md, "jax's compile time"): the same bits.
PARK = 1


@dataclasses.dataclass(frozen=True)
class MaskedSettings:
    """How the masked driver (:func:`run_loop`) runs, held by the jax backend (``backend.settings``)
    and recorded with every result row (``driver_json``).  None of them changes a per-ray result
    except ``ladder``, which is part of the algorithm.

    chunk:    rays per ``lax.map`` chunk;  ratio: batch shrink factor from level to level;
    last:     the smallest level's batch;  last_constant: the smallest level's batch of a
              constant-step march (:func:`constant_steps`; at least ``last``);
    tail_cap: steps of a chunk's last level before its stragglers join those of every chunk;
    ladder:   samples per ladder step where the knob ``ladder`` is -1 (the driver's choice);
    pad:      a batch of n rays runs as :func:`padded_size` ``(n, pad)`` rows, the next power of two
              of at least ``pad`` (copies of the first ray, their results dropped), so that ray sets
              of nearby sizes share one compiled kernel; 0: run n rows as they are.  The catalog's
              ray counts are powers of two ≥ 64, so its rows run no padding row;
    park:     1: the levels compact only the stages that search for a crossing, and a root finder's
              refinement and certification stages run once on the whole chunk after them
              (:func:`run_loop`); 0: every stage in every level."""

    chunk: int = CHUNK
    ratio: int = RATIO
    last: int = LAST
    last_constant: int = LAST_CONSTANT
    tail_cap: int = TAIL_CAP
    ladder: int = LADDER
    pad: int = PAD
    park: int = PARK

    kind = "masked"

    def __post_init__(self):
        for f in dataclasses.fields(self):
            _whole_at_least(type(self).__name__, f.name, getattr(self, f.name),
                            0 if f.name in ("ladder", "pad", "park") else (2 if f.name == "ratio" else 1))
        if self.park not in (0, 1):
            raise ValueError(f"{type(self).__name__}: park must be 0 or 1 (levels for every stage, or for the "
                             f"searching stages only), got {self.park!r}")

    def record(self) -> dict:
        """The settings as recorded with a result: ``{"driver": kind, field: value, …}``."""
        return {"driver": self.kind, **dataclasses.asdict(self)}


def constant_steps(alg) -> bool:
    """Whether ``alg`` marches with constant steps (:class:`impls.core.rootfind.ConstantStep`)."""
    return isinstance(getattr(alg, "rule", None), rootfind.ConstantStep)


def smallest_level(alg, settings: MaskedSettings) -> int:
    """The smallest level's batch for ``alg``: ``settings.last``, or for a constant-step march
    the larger of it and ``settings.last_constant``."""
    return max(settings.last, settings.last_constant) if constant_steps(alg) else settings.last


def padded_size(n: int, pad: int = PAD) -> int:
    """Rows a batch of ``n`` rays runs as: the next power of two ≥ max(n, pad); ``n`` itself
    when ``pad`` is 0 or there is no ray."""
    if pad == 0 or n == 0:
        return n
    return 1 << (max(n, pad) - 1).bit_length()


def pad_rows(a, size: int):
    """``a`` (rows first) with copies of its first row appended up to ``size`` rows."""
    extra = size - a.shape[0]
    return a if extra == 0 else jnp.concatenate([a, jnp.broadcast_to(a[:1], (extra,) + a.shape[1:])])


def level_sizes(m: int, ratio: int = RATIO, last: int = LAST) -> list[int]:
    """Batch sizes of the levels of a batch of ``m`` rays: m, ⌈m/ratio⌉, … down to ``last``."""
    sizes = [m]
    while sizes[-1] > last:
        sizes.append(max(-(-sizes[-1] // ratio), last))
    return sizes


def _stages(alg) -> tuple[str, ...]:
    """The stages a masked driver steps: ``alg.masked_stages`` (one step for all of them, every row
    in progress) where the algorithm has them, else ``alg.stages``."""
    return getattr(alg, "masked_stages", None) or alg.stages


def search_stages(alg, park: bool = True) -> int:
    """How many leading stages of ``alg`` the levels compact (:func:`_levels`): with ``park``, its
    searching stages (``alg.search_stages``: marching, the ladder) where it has stages after them
    (refinement, certification) and its refiner needs no derivative, which then run once on the
    whole chunk after the levels (:func:`_run`); else all of its stages."""
    n = len(_stages(alg))
    if getattr(alg, "deriv", False):
        # Newton's refinement: a step evaluates φ and dφ/dt, and its safeguarded iterations have a
        # tail; run on the whole chunk it cost ×1.08–1.24 at 1,024 rays for 0.1–0.2 s of compile
        # (docs/performance.md), so its refinement keeps the levels
        return n
    k = getattr(alg, "search_stages", n) if getattr(alg, "masked_stages", None) is None else n
    return k if park and 0 < k < n else n


def _stage_loops(alg, s: dict, o, d, ev, keep: int, cap: int | None, ks: range, choice=None) -> dict:
    """Step the rays of ``s`` stage by stage (the stages of indices ``ks``), each
    stage while more than ``keep`` of its rays are iterating (and, with ``cap``, for at most
    ``cap`` steps); other rows keep their values.  ``choice``: ``(index, algorithms)``, each step
    that of ``algorithms[index]`` (``lax.switch`` in the loop's body)."""
    masked = getattr(alg, "masked_stages", None)  # (one step for all of the stages: every row in progress)
    names = _stages(alg)
    for k in ks:
        step = getattr(alg, names[k])
        if choice is not None:
            def step(xp, c, o, d, ev, name=names[k]):
                branches = [lambda c, a=a: {key: v for key, v in getattr(a, name)(xp, c, o, d, ev).items() if key in c}
                            for a in choice[1]]
                return lax.switch(choice[0], branches, c)

        def active(c, k=k):
            return (c["status"] == rootfind.IN) & (True if masked else c["phase"] == k)

        def body(c, step=step, active=active):
            new = step(jnp, c, o, d, ev)
            a = active(c)
            return {key: jnp.where(a, new[key], c[key]) for key in c}

        if cap is None:
            s = lax.while_loop(lambda c, active=active: jnp.sum(active(c)) > keep, body, s)
        else:
            s = lax.while_loop(lambda c, active=active: (jnp.sum(active(c[0])) > keep) & (c[1] < cap),
                               lambda c, body=body: (body(c[0]), c[1] + 1), (s, 0))[0]
    return s


def _gather(s: dict, o, d, mask, size: int):
    """The first ``size`` rows where ``mask`` (indices ``sel``, = m past the last one), as a
    batch whose padding rows are marked finished."""
    m = mask.shape[0]
    sel = jnp.nonzero(mask, size=size, fill_value=m)[0]
    g = jnp.minimum(sel, m - 1)
    sub = {k: v[g] for k, v in s.items()}
    sub["status"] = jnp.where(sel < m, sub["status"], rootfind.CONV)
    return sel, sub, o[g], d[g]


def _levels(alg, s: dict, o, d, ev, sizes: list[int], cap: int | None, searching: int):
    """Run the searching stages (the first ``searching`` of :func:`_stages`) of the rays of state
    ``s`` (a batch of ``sizes[0]`` rows, rays ``o``, ``d``); returns ``(state, rest)``.

    This level's loop for stage k runs while more than ``sizes[1]``/``searching`` rays are in
    stage k, so at most ``sizes[1]`` rays are left searching; they are gathered into a batch of
    that size (``jnp.nonzero`` with a static ``size``; padding rows are marked finished) and run
    by the next level, skipped (``lax.cond``) when no ray is left; their states are scattered
    back.  The last level runs the searching stages to the end (``cap`` None; ``rest`` is None)
    or for at most ``cap`` steps per stage: ``rest = (idx, state, o, d)`` is then that last
    batch, ``idx`` the indices in ``s`` of its rows still searching (= ``sizes[0]`` for the
    others, whose rows there are marked finished), for the caller to finish.  A ray past the
    searching stages waits in ``s`` for the later ones (:func:`_run`).  Per-ray results do not
    depend on the levels: each ray's iteration is independent of the others."""
    m = sizes[0]
    last = len(sizes) == 1
    s = _stage_loops(alg, s, o, d, ev, 0 if last else sizes[1] // searching, cap if last else None, range(searching))
    left = s["status"] == rootfind.IN
    if searching < len(_stages(alg)):  # (a masked algorithm's phase is its own: all of its stages search)
        left = left & (s["phase"] < searching)
    if last:
        if cap is None:
            return s, None
        rest = dict(s, status=jnp.where(left, s["status"], rootfind.CONV))
        return s, (jnp.where(left, jnp.arange(m), m), rest, o, d)

    def next_level(s):
        sel, sub, oc, dc = _gather(s, o, d, left, sizes[1])
        res, rest = _levels(alg, sub, oc, dc, ev, sizes[1:], cap, searching)
        s = {k: v.at[sel].set(res[k], mode="drop") for k, v in s.items()}
        if rest is not None:  # indices in sub → in s (sub's padding index sizes[1] → m)
            rest = (jnp.append(sel, m)[rest[0]],) + rest[1:]
        return s, rest

    def done(s):  # nothing left: a rest of the same shape, all padding
        return s, (None if cap is None else _gather(s, o, d, jnp.zeros_like(left), sizes[-1]))

    return lax.cond(jnp.any(left), next_level, done, s)


def _run(alg, s: dict, o, d, ev, sizes: list[int], cap: int | None, searching: int, later=None):
    """The searching stages level by level (:func:`_levels`), then the later stages (refinement,
    certification) on the whole batch, each to the end; returns ``(outputs, rest)``.  ``later``:
    ``(index, algorithms)``, the later stages those of ``algorithms[index]`` (:func:`run_loop`)."""
    s, rest = _levels(alg, s, o, d, ev, sizes, cap, searching)
    ks = range(searching, len(_stages(alg)))
    if later is None:
        s = _stage_loops(alg, s, o, d, ev, 0, None, ks)
    else:
        # the entries another refiner holds that this search did not make (the secant's bracket
        # width at its last check, after bisection's search), made from the bracket [a, b] as its
        # own search makes them on a crossing (a ray not refining never reads them); the loops
        # carry what the steps of any of the algorithms read (alg.reads) and the status and phase
        # every step writes, and each step is the one ``later`` picks (lax.switch in the loop's
        # body: a switch around the loops ran ×1.15 slower, measured on the CSG camera)
        made = {k: v for a in later[1] for k, v in a.refiner.on_bracket(jnp, s["b"] - s["a"]).items() if k not in s}
        keep = frozenset({"status", "phase"}).union(*(a.reads(_stages(a)[k]) for a in later[1] for k in ks))
        sub = _stage_loops(alg, {k: v for k, v in {**s, **made}.items() if k in keep}, o, d, ev, 0, None, ks,
                           choice=later)
        s = {**s, **{k: v for k, v in sub.items() if k in s}}
    return rootfind.outputs(jnp, s), rest


def check_later(alg, algorithms, park: bool) -> None:
    """That ``algorithms`` may finish what ``alg`` searched (:func:`run_loop`'s ``later``): the same
    class, stages and searching stages as ``alg``, stages after the search, no refiner that needs
    derivatives (whose refinement keeps the levels: :func:`search_stages`), and ``park`` on
    (without it every stage runs in the levels, and there is nothing later)."""
    if not park:
        raise ValueError("run_loop: later needs park (without it every stage runs level by level)")
    stages, searching = _stages(alg), search_stages(alg, park)
    for a in algorithms:
        if getattr(a, "deriv", False):
            raise ValueError(f"run_loop: later's algorithms must need no derivative (a {type(a.refiner).__name__} "
                             "refinement keeps the levels)")
        if type(a) is not type(alg) or _stages(a) != stages or search_stages(a, park) != searching:
            raise ValueError(f"run_loop: later's algorithms must be {type(alg).__name__}s with the stages {stages} and "
                             f"{searching} searching stage(s); got {type(a).__name__} with {_stages(a)}")
        if searching == len(stages):
            raise ValueError("run_loop: later's algorithms must have stages after their search")


def run_loop(alg, o, d, ev, chunk: int = CHUNK, ratio: int = RATIO, last: int = LAST,
             tail_cap: int = TAIL_CAP, park: bool = True, later=None) -> dict:
    """Run ``alg`` on every ray; returns the per-ray outputs.

    Per-ray step counts are heavy-tailed (grazing rays need thousands of steps, most rays a
    few), and a fixed-shape loop runs as long as its slowest ray, so the rays still iterating
    are compacted into ever smaller batches (:func:`_levels`), chunk by chunk (``lax.map``
    over chunks of ``chunk`` rays keeps each chunk's state in cache).  With ``park`` the levels
    compact only the stages that search for a crossing (:func:`search_stages`): the brackets'
    refinement and certification take a few dozen steps on every ray that crossed, not a heavy
    tail, and run once on the whole chunk after its levels (every level is a copy of the loops
    of the stages it runs: docs/performance.md).  With several chunks, each chunk's last level
    stops after ``tail_cap`` steps and the stragglers of all chunks are finished together, again
    level by level.  The algorithm is a per-ray state machine, so the results do not depend on
    chunks, levels, caps or ``park``.

    ``later``: ``(index, algorithms)``, algorithms that differ from ``alg`` in what they do after
    the search only (the constant-step marchers' refiners: :func:`impls.jax.backend.march_switch`),
    checked by :func:`check_later`: ``alg`` starts and searches, and the later stages are those of
    ``algorithms[index]``, an index that may be traced (``lax.switch`` in each loop's body), so
    that one program holds them all.  What another refiner holds and ``alg``'s search did not make
    is made at the hand-off from the bracket (the refiner's ``on_bracket``, as its own search
    makes it on a crossing)."""
    n = o.shape[0]
    if later is not None:
        check_later(alg, later[1], park)
    if n == 0:
        return rootfind.outputs(jnp, alg.init(jnp, o, d, ev))
    searching = search_stages(alg, park)
    chunk = min(chunk, n)
    rows = -(-n // chunk) * chunk  # whole chunks: copies of the first ray, their results dropped
    o, d = pad_rows(o, rows), pad_rows(d, rows)
    sizes = level_sizes(chunk, ratio, last)
    n_chunks = o.shape[0] // chunk
    cap = tail_cap if n_chunks > 1 else None
    out, rest = lax.map(lambda od: _run(alg, alg.init(jnp, od[0], od[1], ev), od[0], od[1], ev, sizes, cap, searching,
                                        later), (o.reshape(-1, chunk, 3), d.reshape(-1, chunk, 3)))
    out = {k: v.reshape(-1) for k, v in out.items()}
    if rest is not None:  # the stragglers of every chunk, finished together
        idx, s, oc, dc = rest
        starts = (jnp.arange(n_chunks) * chunk)[:, None]
        idx = jnp.where(idx < chunk, idx + starts, o.shape[0]).reshape(-1)
        s = {k: v.reshape(-1) for k, v in s.items()}
        res, _ = _run(alg, s, oc.reshape(-1, 3), dc.reshape(-1, 3), ev, level_sizes(idx.shape[0], ratio, last), None,
                      searching, later)
        out = {k: v.at[idx].set(res[k], mode="drop") for k, v in out.items()}
    return {k: v[:n] for k, v in out.items()}
