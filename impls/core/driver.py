"""Loop driver with active-set compaction for eager backends (numpy, torch): runs a staged
root finder of :mod:`impls.core.rootfind` to completion.

Why it looks the way it does (each choice checked with `python -m bench speed`):

* **Structure of arrays.**  Origins and directions are kept as contiguous (3, n) arrays and
  passed to the algorithm as their transposed (n, 3) views, so x = o + t d and every scene's
  ``xp.sum(v * v, axis=-1)`` run over three contiguous rows instead of a stride-3 axis (numpy's
  strided short-axis loops dominate a CSG φ otherwise).
* **Blocks.**  Rays go through in blocks of ``block``, which bounds the memory of the state.
  Larger blocks mean fewer Python-level steps (a step's cost is mostly per-call overhead on
  small blocks); the default 2^16 keeps a block's state in cache.
* **Compaction.**  Within a block only rays still iterating in the current stage are stepped;
  a ray's outputs are written the step it finishes, so ``evals`` counts exactly the
  evaluations made.  The rays that stay are compacted in place by moving the last ones into
  the holes (:func:`_drop`, O(leaving) per array) rather than gathered (O(staying)), since
  few rays leave per step.  A block's rays that finish at the start (outside the ray
  bounds, ``alg.start``) are dropped the same way before φ is evaluated (``alg.init`` runs on
  the others only), and rays handed on to a later stage are gathered into that stage's
  bucket.  Rows are gathered with ``take`` (numpy's fancy indexing ``Oc[:, sel]`` of a
  (3, n) array is the slower path) and moved row by row.
* **Carry only what is read.**  A stage's rows carry only the state entries its step reads
  (``alg.reads``): every step writes ``status`` and ``phase`` afresh, and a refining ray
  has no use for its marching step size or bound, so moving them would be wasted copying.
* **Threads.**  ``workers`` threads run blocks side by side (``--threads`` of the bench
  commands): numpy releases the GIL inside its kernels, so blocks overlap; torch gains little
  (its per-call overhead holds the GIL).
* **Straggler pool.**  Per-ray step counts are heavy-tailed (grazing rays).  Once fewer than
  ``pool`` rays of a block remain in a stage, they are set aside and finished together with
  the stragglers of every other block, so the long tail costs its loop overhead once, not once
  per block.  Per-ray results do not depend on the block or pool (each ray's iteration is
  independent of the others).
"""

from __future__ import annotations

import contextlib
import dataclasses
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable

from .rootfind import IN, STATE_OUT, final_t


def _whole_at_least(owner: str, name: str, value: Any, low: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise ValueError(f"{owner}: {name}={value!r} must be a whole number ≥ {low}")


@dataclasses.dataclass(frozen=True)
class CompactingSettings:
    """How the compacting driver (:func:`run_compacted`) runs, held by a numpy or torch backend
    (``backend.settings``) and recorded with every result row (``driver_json``).  None of them
    changes a per-ray result except ``ladder``, which is part of the algorithm.

    threads: worker threads running blocks side by side (``--threads`` of the bench commands).
    block:   rays per block (state in cache, few Python-level steps; see the module docstring).
    pool:    a stage's last rays of a block, fewer than this, join the straggler pool (0: none).
    ladder:  samples per ladder step (:class:`impls.core.rootfind.MarchRefine`) where the knob
             ``ladder`` is -1, "the driver's choice": 16 — once few rays are left, a compacting
             loop step costs its per-call overhead whatever their number."""

    threads: int = 1
    block: int = 1 << 16
    pool: int = 4096
    ladder: int = 16

    kind = "compacting"

    def __post_init__(self):
        for f in dataclasses.fields(self):
            _whole_at_least(type(self).__name__, f.name, getattr(self, f.name), 0 if f.name in ("ladder", "pool") else 1)

    def record(self) -> dict:
        """The settings as recorded with a result: ``{"driver": kind, field: value, …}``."""
        return {"driver": self.kind, **dataclasses.asdict(self)}


def run_compacted(alg, xp, o, d, ev, *, soa: Callable[[Any], Any], block: int = 1 << 16, pool: int = 4096,
                  workers: int = 1, guard: Callable[[], Any] = contextlib.nullcontext,
                  take: Callable[[Any, Any, int], Any] | None = None,
                  move: Callable[[Any, Any, Any], None] | None = None) -> dict:
    """Run ``alg`` on rays ``o``, ``d`` (n, 3); returns ``{t, status, iterations, evals}`` (n,).

    ``soa(a)`` returns a contiguous (3, n) copy of an (n, 3) array (backend-specific: the array
    API has no contiguity control; always a copy, which the blocks compact in place).
    ``workers`` > 1 runs the blocks on that many threads:
    numpy and torch release the GIL inside their array operations, so blocks overlap; each
    thread writes only its own rays' outputs.  The straggler pool then runs on one thread: its
    steps are on few rays, where the per-call overhead (under the GIL) dominates, and split
    over two threads it measured slower.  ``guard()`` is entered in every thread (numpy's
    ``errstate`` and torch's ``no_grad`` are per thread).  ``take(a, indices, axis)`` gathers
    rows (default ``xp.take``; torch passes ``index_select``: array_api_compat's ``take`` also
    wraps negative indices, which costs a pass); ``move(v, holes, src)`` does
    ``v[holes] = v[src]`` in place (torch passes ``index_copy_``, which skips advanced indexing's
    checks).
    """
    n = o.shape[0]
    if take is None:
        def take(a, idx, axis):
            return xp.take(a, idx, axis=axis)
    if move is None:
        def move(v, holes, src):
            v[holes] = v[src]
    O, D = soa(o), soa(d)
    out: dict = {}
    lock = threading.Lock()
    pools: list[list] = [[] for _ in alg.stages]

    def run_block(start):
        with guard():
            stop = min(start + block, n)
            Ob, Db = O[:, start:stop], D[:, start:stop]
            t, hi, status = alg.start(xp, Ob.T, Db.T)
            with lock:
                if not out:
                    out.update(t=xp.empty((n,), dtype=t.dtype, device=t.device),
                               **{k: xp.empty((n,), dtype=xp.int32, device=t.device) for k in STATE_OUT[1:]})
            out["t"][start:stop] = final_t(xp, t, status)
            out["status"][start:stop] = status
            out["iterations"][start:stop] = 0
            out["evals"][start:stop] = 0
            s, gidx = {"t": t, "hi": hi, "status": status}, xp.arange(start, stop, device=t.device)
            # the rays that finish at the start (MISS outside the ray bounds, BAD_INPUT) leave before
            # φ is evaluated, in place, O(finished): the block's own slice of O, D and its fresh state
            s, gidx, Ob, Db = leave_finished(s, gidx, Ob, Db, None, write=False)
            if gidx.shape[0]:
                s = alg.init(xp, Ob.T, Db.T, ev, start=(s["t"], s["hi"], s["status"]))
                # and those that init's evaluation finishes (φ = 0 or not finite at the start)
                s, gidx, Ob, Db = leave_finished(s, gidx, Ob, Db, _reads(alg, 0), write=True)
            if gidx.shape[0]:
                _run_stages(alg, xp, take, move, s, gidx, Ob, Db, ev, out, 0, pools, pool)

    def leave_finished(s, gidx, Ob, Db, keys, write: bool):
        done = s["status"] != IN
        n_done = int(xp.count_nonzero(done))
        if not n_done:
            return s, gidx, Ob, Db
        if write:
            _write(xp, take, out, s, gidx, _nonzero(xp, done))
        return _drop(xp, move, s, gidx, Ob, Db, done, n_done, keys)

    def run_pool(k, part):
        with guard():
            _run_stages(alg, xp, take, move, *part, ev, out, k, None, 0)

    starts = range(0, max(n, 1), block)
    if workers <= 1:
        for start in starts:
            run_block(start)
    else:
        with ThreadPoolExecutor(workers) as ex:
            list(ex.map(run_block, starts))  # list(): re-raises a worker's exception here
    for k, parts in enumerate(pools):  # stage by stage: a pool run hands rays on to later stages itself
        if parts:
            run_pool(k, _concat(xp, parts))
    return out


def _reads(alg, k: int):
    """The state entries stage ``k`` reads (``alg.reads``, :meth:`impls.core.rootfind.MarchRefine.reads`),
    the only ones carried into and through it; None (all) for an algorithm that does not say.
    Arrays moved per leaving ray (with the 7 rows of ray index, origin and direction): marching
    17 → 15, refinement 21 → 16 (a refining ray no longer carries its marching step size, bound,
    phase, status and φ at the bracket's second end); one more each since the state carries
    |o|₁ + scale (``mag``), which the steps read instead of recomputing it."""
    reads = getattr(alg, "reads", None)
    return None if reads is None else reads(alg.stages[k])


def _take(take, s: dict, gidx, Oc, Dc, sel, keys=None):
    """The rows ``sel`` (indices) of every array (of the state entries ``keys``; None: all),
    gathered with ``take`` (numpy's fast path for gathering rows, unlike fancy indexing).  Every entry is gathered on its own, also where a step stored one array under two
    names (a marching step's ``b`` and ``t`` on a crossing): the copies are then distinct."""
    new = {k: take(v, sel, 0) for k, v in s.items() if keys is None or k in keys}
    return new, take(gidx, sel, 0), take(Oc, sel, 1), take(Dc, sel, 1)


def _drop(xp, move, s: dict, gidx, Oc, Dc, leave, k: int, keys=None):
    """Remove the rows in ``leave`` in place: the kept rows of the tail move into the holes the
    leaving rows open in the first m − k places (k = ``leave.sum()``), then every array is cut
    to its first m − k rows; state entries not in ``keys`` (None: all are kept) are dropped.
    Cost O(k) per array instead of the O(m) of gathering the kept rows; the order of the rays
    changes, which no per-ray result depends on.  Every array here is owned by the loop (stage
    entry and hand-off gather copies).  Entries are moved one by one; two entries holding one
    array (``init`` starts the bracket and the secant's previous point at t) are moved twice
    with the same result, since holes and sources are disjoint rows.  ``move(v, holes, src)``
    does v[holes] = v[src]."""
    kept = gidx.shape[0] - k
    holes = _nonzero(xp, leave[:kept])
    src = _nonzero(xp, ~leave[kept:]) + kept
    if keys is not None:
        s = {key: v for key, v in s.items() if key in keys}
    for v in (*s.values(), gidx, *Oc, *Dc):  # row by row: numpy's 2-D Oc[:, holes] is 3× slower
        move(v, holes, src)
    return {key: v[:kept] for key, v in s.items()}, gidx[:kept], Oc[:, :kept], Dc[:, :kept]


def _write(xp, take, out: dict, s: dict, gidx, rows) -> None:
    """Write the outputs of the finished ``rows`` (indices) into ``out`` at their global indices."""
    gi = take(gidx, rows, 0)
    got = {key: take(s[key], rows, 0) for key in STATE_OUT}
    got["t"] = final_t(xp, got["t"], got["status"])
    for key in STATE_OUT:
        out[key][gi] = got[key]


def _concat(xp, parts):
    if len(parts) == 1:
        return parts[0]
    s = {k: xp.concat([p[0][k] for p in parts]) for k in parts[0][0]}
    return (s, xp.concat([p[1] for p in parts]), xp.concat([p[2] for p in parts], axis=1),
            xp.concat([p[3] for p in parts], axis=1))


def _nonzero(xp, mask):
    return xp.nonzero(mask)[0]


def _run_stages(alg, xp, take, move, s, gidx, Oc, Dc, ev, out, k0, pools, pool):
    """Run stages ``k0, k0+1, …`` on the rays of ``s`` (rows of the (3, m) ``Oc``/``Dc``, global
    indices ``gidx``), every one of them in progress in stage ``k0``, on arrays the loop owns
    (they are compacted in place); write finished rays into ``out``; with ``pools``, set a
    stage's last < ``pool`` rays aside in ``pools[k]`` instead of finishing them here.  A stage
    may hand a ray on to any later stage (a marching step that crosses goes straight to
    refinement): rays handed on wait in their stage's bucket."""
    n_stages = len(alg.stages)
    reads = [_reads(alg, k) for k in range(n_stages)]
    buckets: list[list] = [[] for _ in range(n_stages)]
    buckets[k0].append((s, gidx, Oc, Dc))
    for k in range(k0, n_stages):
        if not buckets[k]:
            continue
        step = getattr(alg, alg.stages[k])
        s, gidx, Oc, Dc = _concat(xp, buckets[k])
        while gidx.shape[0]:
            s = step(xp, s, Oc.T, Dc.T, ev)
            fin = s["status"] != IN
            last = k + 1 == n_stages  # (the last stage's step need not write a phase)
            moved = None if last else s["phase"] != k  # handed on to a later stage
            leave = fin if last else fin | moved
            n_leave = int(xp.count_nonzero(leave))  # the step's one host sync
            if not n_leave:
                continue
            fi = _nonzero(xp, fin)
            if fi.shape[0]:
                _write(xp, take, out, s, gidx, fi)
            if fi.shape[0] < n_leave:
                on = moved & ~fin
                later = range(k + 1, n_stages)
                for k2 in later:
                    sel = _nonzero(xp, on if len(later) == 1 else on & (s["phase"] == k2))
                    if sel.shape[0]:
                        buckets[k2].append(_take(take, s, gidx, Oc, Dc, sel, reads[k2]))
            s, gidx, Oc, Dc = _drop(xp, move, s, gidx, Oc, Dc, leave, n_leave, reads[k])
            if pools is not None and 0 < gidx.shape[0] < pool:
                pools[k].append((s, gidx, Oc, Dc))
                break
