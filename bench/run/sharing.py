"""A run's configurations shared with the second process once its own stages are done.

``bench run`` starts a second process for its accuracy-only stages (the stability stage, the
claims: :mod:`bench.commands._side_stages`) where the machine has a core for it.  Those stages
take about a third of a quick run's configurations' time, so the second process would sit idle
for the rest; instead it then takes configurations from the same plan as this one.

How the plan is shared (:class:`PlanShare`):

* the configurations are grouped by case × backend (:func:`groups_of`, plan order kept inside
  a group), so a process computes a case's reference answers and compiles a kernel structure
  (jax, numba) once for all the knob settings of its sweep, as one process running the whole plan
  does;
* the groups are claimed heaviest first (:func:`heaviest_first`, by a rough estimate of their
  cost), so that the last groups claimed are light ones and neither process runs long alone at
  the end while the other has nothing left;
* this process offers the plan once (:meth:`PlanShare.offer`); each process claims the next
  unclaimed group from a shared counter under a lock, so neither waits for the other to hand
  work out, and a group is run by exactly one process;
* the second process sends each configuration's rows back as it finishes; this process stays
  the run directory's one writer (the runner writes what :class:`SharingExecutor` yields).

Nothing is lost: a configuration the second process claimed but did not report (it died, or
its rows never arrived) is run here once it is known dead.  Timing stays honest as with the
side stages: each process has its own core (``2 × --threads`` cores are required, as for the
side stages), and every row is timed and divided by the closed-form unit in the process that ran
it; rows of the second process say so (``worker`` = :data:`SECOND`, ``worker_pid``).
``--rounds`` > 1 re-times every configuration in this process, so a run with rounds does not
share (the second process only runs its stages).
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import os
import pickle
import queue
import time
from typing import Callable, Iterator

from .configuration import failed_rows
from .executor import InProcessExecutor
from .plan import Config
from .references import ReferenceOptions
from .supervise import hung_for, hung_reason
from .timing import TimingPolicy

#: the ``worker`` of the rows the second process measured
SECOND = "second process"


def groups_of(todo: list[Config]) -> list[list[int]]:
    """Indexes of ``todo`` grouped by (case id, backend id), groups in order of first appearance,
    plan order inside each."""
    groups: dict[tuple[str, str], list[int]] = {}
    for j, cfg in enumerate(todo):
        groups.setdefault((cfg.case.id, cfg.backend_id), []).append(j)
    return list(groups.values())


#: the estimated cost of a method's first configuration in a group, on a backend that compiles
#: kernels (``capabilities.jit``), against 1 on one that does not: compilation, once per kernel
#: structure, is most of a compiling backend's time (a cold quick run: jax's case groups 15–29 s,
#: numpy's and torch's 0.3–7 s)
JIT_WEIGHT = 10.0
#: the estimated cost of a method's further configurations in a group (a knob sweep reuses its
#: kernel), against its first
SWEEP_WEIGHT = 0.1


def heaviest_first(groups: list[list[int]], todo: list[Config], backends: dict) -> list[list[int]]:
    """``groups`` in the order they are to be claimed: estimated cost descending (ties in plan
    order), the longest-processing-time-first rule (Graham 1969, within 4/3 of the best finish
    time of two processes).  A configuration the backend does not run (unavailable, a method it
    does not implement, a dtype it does not support) costs 0; a method's first configuration in
    the group 1, ×``JIT_WEIGHT`` on a backend that compiles; its others ``SWEEP_WEIGHT`` as much.
    The estimate orders work only: every group is run whatever it says, and a backend whose
    methods or capabilities cannot be read counts as compiling every method."""
    from impls import Unavailable

    from .contract import backend_dtypes, backend_methods

    def runs(backend) -> tuple[frozenset, frozenset, float]:
        if isinstance(backend, Unavailable):
            return frozenset(), frozenset(), 0.0
        try:
            jit = bool(getattr(backend.capabilities, "jit", True))
            return frozenset(backend_methods(backend)), frozenset(backend_dtypes(backend)), JIT_WEIGHT if jit else 1.0
        except Exception:  # noqa: BLE001 - a plug-in's broken hooks: its configurations say so when run
            return None, None, JIT_WEIGHT

    seen: dict[str, tuple] = {}

    def cost(group: list[int]) -> float:
        total, methods = 0.0, set()
        for j in group:
            cfg = todo[j]
            if cfg.backend_id not in seen:
                seen[cfg.backend_id] = runs(backends.get(cfg.backend_id))
            names, dtypes, weight = seen[cfg.backend_id]
            if names is not None and (cfg.method not in names or cfg.dtype not in dtypes):
                continue
            total += weight * (SWEEP_WEIGHT if cfg.method in methods else 1.0)
            methods.add(cfg.method)
        return total

    costs = [cost(g) for g in groups]
    return [groups[i] for i in sorted(range(len(groups)), key=lambda i: -costs[i])]


@dataclasses.dataclass
class SharedPlan:
    """What the second process needs to run its share: the configurations still to run, their
    groups, and the run's measuring options (as :meth:`bench.run.executor.Executor.execute` gets
    them)."""

    run_id: str
    todo: list[Config]
    groups: list[list[int]]
    policy: TimingPolicy
    ref_options: ReferenceOptions
    budget_s: float | None
    deadline: float | None
    machine_key: str


class PlanShare:
    """The channel between the two processes: a counter of claimed groups (shared memory, under
    its lock), a queue carrying the plan to the second process (one message: a
    :class:`SharedPlan`, or None when there is nothing to share), and a queue carrying its rows
    back (``("rows", j, rows, over)`` per configuration, then ``("done", closed-form samples)``).
    Made before the second process is started and handed to it as an argument."""

    def __init__(self, ctx=None):
        ctx = ctx or multiprocessing.get_context("spawn")
        self._next = ctx.Value("q", 0)
        self._plan = ctx.Queue()
        self._rows = ctx.Queue()
        self.offered = False

    def claim(self, n_groups: int) -> int | None:
        """The next unclaimed group's index, now this process's to run; None when all are claimed."""
        with self._next.get_lock():
            g = self._next.value
            if g >= n_groups:
                return None
            self._next.value = g + 1
            return g

    # -- this process -------------------------------------------------------------------------
    def offer(self, plan: SharedPlan | None) -> bool:
        """Send the plan (None: nothing to share) to the second process, once; returns whether a
        plan went.  The plan is pickled here, not in the queue's feeder thread: a plan that
        cannot be pickled (a user's scene holding a lambda) is not shared, and the second process
        is told so instead of waiting for it."""
        if self.offered:
            return False
        self.offered = True
        try:
            data = None if plan is None else pickle.dumps(plan)
        except Exception:  # noqa: BLE001 - whatever cannot be pickled is run here, not shared
            data = None
        self._plan.put(data)
        # a second process that died before reading it must not hold this one at exit
        # (a queue's feeder thread is joined at exit until its data is written)
        self._plan.cancel_join_thread()
        return data is not None

    def receive(self, timeout: float | None = None):
        """The second process's next message, or None if none came within ``timeout`` (0: do
        not wait)."""
        try:
            return self._rows.get(timeout=timeout) if timeout else self._rows.get_nowait()
        except queue.Empty:
            return None

    # -- the second process -------------------------------------------------------------------
    def wait_plan(self) -> SharedPlan | None:
        data = self._plan.get()
        return None if data is None else pickle.loads(data)

    def send(self, message) -> None:
        self._rows.put(message)


def serve(share: PlanShare, backends: dict) -> int:
    """The second process's share: wait for the plan, then run the groups it claims, sending
    each configuration's rows as it finishes; returns how many configurations it ran."""
    plan = share.wait_plan()
    if plan is None:
        return 0
    ex = InProcessExecutor(plan.machine_key)
    ref_cache: dict = {"_options": plan.ref_options}
    n = 0
    while (g := share.claim(len(plan.groups))) is not None:
        for j in plan.groups[g]:
            share.send(("start", j, time.time()))  # for the first process's watch on a hang (SharingExecutor)
            rows, over = ex.run_config(plan.run_id, plan.todo[j], backends, plan.policy, ref_cache, plan.budget_s,
                                       plan.deadline)
            share.send(("rows", j, [{**r, "worker": SECOND, "worker_pid": os.getpid()} for r in rows], over))
            n += 1
    share.send(("done", ex.closed_form_samples()))
    return n


class SharingExecutor(InProcessExecutor):
    """:class:`bench.run.executor.InProcessExecutor` whose plan the second process joins once its
    stages are done (:func:`serve`); ``alive()`` says whether the second process is still running."""

    #: seconds between checks that the second process still lives, while waiting for its rows
    POLL_S = 0.2

    def __init__(self, machine_key: str, share: PlanShare, alive: Callable[[], bool],
                 kill: Callable[[], None] | None = None):
        super().__init__(machine_key)
        self.share, self.alive, self.kill = share, alive, kill
        self.n_second = 0
        self._second_done = False  # its "done" arrived, or it was offered nothing
        self._second_at: tuple[int, float] | None = None  # (configuration, time.time() it started) there

    def _take(self, msg, pending: set[int]) -> Iterator[tuple[int, list[dict], bool]]:
        if msg[0] == "start":
            self._second_at = (msg[1], msg[2])
        elif msg[0] == "rows" and msg[1] in pending:
            pending.discard(msg[1])
            self.n_second += 1
            yield msg[1], msg[2], msg[3]
        elif msg[0] == "done":
            for cid, ts in msg[1].items():
                self._cf.setdefault(cid, []).extend(ts)
            self._second_done = True

    def execute(self, run_id, todo, backends, policy, ref_options, budget_s, deadline, on_start=None):
        self._backends = backends
        self._second_done = False
        groups = heaviest_first(groups_of(todo), todo, backends)
        if not self.share.offer(SharedPlan(run_id, todo, groups, policy, ref_options, budget_s, deadline,
                                           self.machine_key)):
            self._second_done = True  # nothing shared: every group is run here
        ref_cache: dict = {"_options": ref_options}
        pending = set(range(len(todo)))  # not yet yielded, whoever runs them
        while (g := self.share.claim(len(groups))) is not None:
            for j in groups[g]:
                while (msg := self.share.receive(0)) is not None:
                    yield from self._take(msg, pending)
                if on_start:
                    on_start(j)
                rows, over = self.run_config(run_id, todo[j], backends, policy, ref_cache, budget_s, deadline)
                pending.discard(j)
                yield j, rows, over
        # the groups the second process claimed: wait for their rows while it lives
        while pending and not self._second_done:
            msg = self.share.receive(self.POLL_S)
            if msg is not None:
                yield from self._take(msg, pending)
            elif (hung := self._hung(pending, policy)) is not None:
                j, hung_s = hung
                pending.discard(j)
                print(f"the second process is stuck in {todo[j].case.id} {todo[j].backend_id} {todo[j].method} "
                      f"({hung_s:.0f} s, its limit {policy.timeout_s:g} s): killing it", flush=True)
                self.kill()
                yield j, failed_rows(run_id, todo[j], backends, hung_reason(float(policy.timeout_s), hung_s)), False
            elif not self.alive():
                while (msg := self.share.receive(0)) is not None:  # what it sent before it died
                    yield from self._take(msg, pending)
                break
        for j in sorted(pending):  # claimed by a second process that died (or lost in transit): run here
            if on_start:
                on_start(j)
            yield (j, *self.run_config(run_id, todo[j], backends, policy, ref_cache, budget_s, deadline))

    def _hung(self, pending: set[int], policy: TimingPolicy) -> tuple[int, float] | None:
        """(configuration, seconds) where the second process has run a configuration of the plan
        long enough past ``--timeout`` to be hung in native code (:func:`bench.run.supervise.hung_for`),
        and this process can kill it; else None."""
        if self._second_at is None or self.kill is None or self._second_at[0] not in pending:
            return None
        j, started = self._second_at
        hung_s = hung_for(started, float(policy.timeout_s or 0.0))
        return None if hung_s is None else (j, hung_s)

    def env_record(self, previous: dict | None = None) -> dict[str, str]:
        return {"configurations_second_process": str(self.n_second)}


__all__ = ["SECOND", "PlanShare", "SharedPlan", "SharingExecutor", "groups_of", "heaviest_first", "serve"]
