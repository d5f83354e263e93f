"""Where configurations run: the :class:`Executor` interface, and :class:`InProcessExecutor`,
which runs them in this process one after the other.  :class:`bench.run.cluster.ClusterExecutor`
runs them as tasks on a dask cluster.

The runner (:func:`bench.run.runner.run`) has one loop whatever the executor: it plans, hands
the configurations still to run to :meth:`Executor.execute`, writes the rows it yields, and asks
the executor for the extra timing rounds of ``--rounds`` and for what environment.json records
of it.  The executor decides where and in which order configurations run; the runner stays the
one writer of the run directory.
"""

from __future__ import annotations

import time
from typing import Callable, Iterator, Protocol

import numpy as np

from .configuration import closed_form_time, pool, retime, run_budgeted
from .plan import Config
from .references import ReferenceOptions
from .timing import TimingPolicy


class Interrupted(RuntimeError):
    """An executor could not finish the plan (its cluster went away): the run keeps what
    finished, is marked incomplete with this message, and ``--resume`` finishes it."""


class Executor(Protocol):
    """Runs the configurations of a plan somewhere and gives their rows back."""

    def execute(self, run_id: str, todo: list[Config], backends: dict, policy: TimingPolicy,
                ref_options: ReferenceOptions, budget_s: float | None, deadline: float | None,
                on_start: Callable[[int], None] | None = None) -> Iterator[tuple[int, list[dict], bool]]:
        """Yield ``(index in todo, rows, over budget)`` for every configuration of ``todo``, in
        the order they finish.  ``deadline``: the run's budget as a ``time.time()`` (None: none);
        a configuration that starts past it is one skipped over-budget row.  ``on_start(j)``:
        called as configuration ``j`` starts, where the executor knows it (in this process).
        Raises :class:`Interrupted` when the rest cannot run."""
        ...

    def retime_rounds(self, rows: list[dict], todo: list[Config], rounds: int, run_id: str, policy: TimingPolicy,
                      progress: Callable[..., None] | None, counts: dict, inflight=None) -> None:
        """``--rounds``: rounds 2… of every measured configuration of ``todo``, their samples
        pooled into ``rows`` (:func:`bench.run.configuration.pool`) with the closed-form unit
        of the same process.  ``inflight`` (the run's in-flight note, where the configurations
        run in this process): told each configuration as it is timed again, so that a crash or a
        native hang in a later round is seen by the supervising process as in the first."""
        ...

    def closed_form_samples(self) -> dict[str, list[float]]:
        """Closed-form seconds per case measured so far (environment.json records the median)."""
        ...

    def env_record(self, previous: dict | None = None) -> dict[str, str]:
        """What environment.json records of the executor; ``previous``: the run's environment
        so far (a resumed session adds to it)."""
        ...


class InProcessExecutor:
    """Configurations in this process, one after the other, in plan order; the closed-form unit
    measured once per case (and once more per extra round); every row records this machine's
    key and the configuration's wall seconds (``task_s``)."""

    def __init__(self, machine_key: str):
        self.machine_key = machine_key
        self._cf: dict[str, list[float]] = {}
        self._backends: dict = {}

    def _cf_time(self, cfg: Config, policy: TimingPolicy) -> float:
        if policy.accuracy_only:
            return float("nan")
        if cfg.case.id not in self._cf:
            self._cf[cfg.case.id] = [closed_form_time(cfg.case, policy)]
        return self._cf[cfg.case.id][0]

    def run_config(self, run_id: str, cfg: Config, backends: dict, policy: TimingPolicy, ref_cache: dict,
                   budget_s: float | None, deadline: float | None) -> tuple[list[dict], bool]:
        """One configuration here, under what is left of the run's budget: (rows, over budget),
        each row with this machine's key and the configuration's wall seconds (``task_s``)."""
        left = None if deadline is None else deadline - time.time()
        t0 = time.perf_counter()
        got, over = run_budgeted(run_id, cfg, backends[cfg.backend_id], policy,
                                 lambda: self._cf_time(cfg, policy), ref_cache, budget_s, left)
        task_s = time.perf_counter() - t0
        return [{**r, "machine_key": self.machine_key, "task_s": task_s} for r in got], over

    def execute(self, run_id, todo, backends, policy, ref_options, budget_s, deadline, on_start=None):
        self._backends = backends  # the extra rounds time the same backend objects
        ref_cache: dict = {"_options": ref_options}  # reference answers shared by the plan's configurations
        for j, cfg in enumerate(todo):
            if on_start:
                on_start(j)
            yield (j, *self.run_config(run_id, cfg, backends, policy, ref_cache, budget_s, deadline))

    def retime_rounds(self, rows, todo, rounds, run_id, policy, progress, counts, inflight=None):
        index: dict[tuple, list[int]] = {}
        for j, r in enumerate(rows):
            if r.get("outcome") == "ok" and r.get("run_id") == run_id:
                index.setdefault((r["case_id"], r["backend"], r["dtype"], r["method"], r["knob"]), []).append(j)
        todo_ok = [c for c in todo if tuple(map(str, c.key)) in index]
        for rnd in range(2, rounds + 1):
            for i, cfg in enumerate(todo_ok):
                samples = self._cf.setdefault(cfg.case.id, [])
                if len(samples) < rnd:  # this round's closed-form sample, beside the round's timings
                    samples.append(closed_form_time(cfg.case, policy))
                if progress:
                    progress(i, len(todo_ok), f"round {rnd}/{rounds}: {cfg.case.id} {cfg.backend_id} {cfg.method}",
                             counts)
                if inflight is not None:
                    inflight.start(cfg, f"round {rnd}/{rounds}: {cfg.case.id} {cfg.backend_id} {cfg.dtype} {cfg.method}")
                extra = retime(cfg, self._backends[cfg.backend_id], policy)
                if inflight is not None:
                    inflight.end(cfg)
                for j in index[tuple(map(str, cfg.key))]:
                    pool(rows[j], extra, float(np.median(samples)))

    def closed_form_samples(self) -> dict[str, list[float]]:
        return {cid: list(ts) for cid, ts in self._cf.items()}

    def env_record(self, previous: dict | None = None) -> dict[str, str]:
        return {}

