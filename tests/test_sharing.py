"""A run's plan shared with the second process once its stages are done (bench/run/sharing.py):
every configuration gives its rows exactly once, whichever process ran it, with the same
accuracy as one process running the whole plan; a second process that dies with groups claimed
loses nothing; the groups keep a case × backend together."""

from __future__ import annotations

import threading

import pandas as pd

from bench.run import runner
from bench.run.plan import plan
from bench.run.sharing import SECOND, PlanShare, groups_of, serve
from bench.run.suites import Suite
from bench.run.timing import TimingPolicy
from impls import registry

SUITE = Suite("t", "sphere.camera.64x64,torus.camera.32x32", ("float64",),
              {"sphere_trace": [{"tol": 1e-4}, {"tol": 1e-8}], "hybrid_secant": [{"xtol": 1e-6}, {"xtol": 1e-10}],
               "normal": [{}]}, methods=("sphere_trace", "hybrid_secant", "normal"))
POLICY = TimingPolicy(accuracy_only=True)
KEY = ["case_id", "backend", "dtype", "method", "knob", "quantity"]
ACCURACY = ["outcome", "error_max", "evals_per_ray", "status_counts", "n_false_hit", "n_false_miss"]


def _backends():
    return {"numpy": registry.resolve("numpy"), "torch:cpu": registry.resolve("torch:cpu")}


def test_groups_keep_a_case_and_backend_together_in_plan_order():
    todo = plan(SUITE, list(_backends()), None, None, None)
    groups = groups_of(todo)
    assert sorted(j for g in groups for j in g) == list(range(len(todo)))  # each configuration once
    for g in groups:
        assert g == sorted(g)
        assert len({(todo[j].case.id, todo[j].backend_id) for j in g}) == 1
    assert len(groups) == len({(c.case.id, c.backend_id) for c in todo})


def test_a_shared_plan_gives_every_row_once_with_one_process_accuracy(tmp_path):
    """The second process is a thread here (the channel is the same); it joins at once, so it
    takes groups while this process runs its own."""
    backends = _backends()
    alone = runner.run(SUITE, backends, tmp_path / "alone", policy=POLICY)
    share = PlanShare()
    second = threading.Thread(target=serve, args=(share, _backends()), daemon=True)
    second.start()
    shared = runner.run(SUITE, backends, tmp_path / "shared", policy=POLICY, share=(share, second.is_alive))
    second.join(60)
    assert not second.is_alive()
    assert len(shared) == len(alone) and not shared.duplicated(KEY).any()
    assert (shared["worker"] == SECOND).any(), "the second process ran nothing"
    assert (shared["worker"] != SECOND).any(), "this process ran nothing"
    m = alone.merge(shared, on=KEY, suffixes=("", "_shared"))
    assert len(m) == len(alone)
    for col in ACCURACY:
        a, b = m[col], m[f"{col}_shared"]
        assert ((a == b) | (a.isna() & b.isna())).all(), col
    env = pd.read_json(tmp_path / "shared" / "environment.json", typ="series")
    assert int(env["configurations_second_process"]) == int((shared["worker"] == SECOND).groupby(
        [shared[k] for k in KEY[:-1]]).any().sum())


def test_groups_claimed_by_a_second_process_that_died_are_run_here(tmp_path):
    """A second process that claimed groups and died before reporting them: this process runs
    them once it sees it dead; nothing is lost or run twice."""
    backends = _backends()
    share = PlanShare()
    n_groups = len(groups_of(plan(SUITE, list(backends), None, None, None)))
    for _ in range(2):  # the dead process's claims (it never sends a row)
        assert share.claim(n_groups) is not None
    df = runner.run(SUITE, backends, tmp_path, policy=POLICY, share=(share, lambda: False))
    alone = runner.run(SUITE, backends, tmp_path / "alone", policy=POLICY)
    assert len(df) == len(alone) and not df.duplicated(KEY).any()
    assert set(df["outcome"]) == set(alone["outcome"])
    assert not (df["worker"] == SECOND).any()


def test_rounds_do_not_share(tmp_path):
    """``--rounds`` re-times every configuration in this process: no plan is offered."""
    share = PlanShare()
    runner.run(SUITE, {"numpy": registry.resolve("numpy")}, tmp_path,
               policy=TimingPolicy(min_repeats=1, min_time_s=0.0, warmup=0), rounds=2, share=(share, lambda: True))
    assert not share.offered


def test_a_plan_that_cannot_be_pickled_is_not_shared_and_the_second_process_is_told():
    """A user's scene holding a lambda cannot cross to the second process: the plan is not
    offered (this process runs it all) and the second process, waiting for a plan, gets None
    instead of waiting for ever."""
    share = PlanShare()
    assert share.offer(lambda: 0) is False  # pickled here, not in the queue's feeder thread
    assert share.wait_plan() is None
    assert share.offer(None) is False  # once only


class _Fake:
    """A backend as far as the claim order reads one: its methods and capabilities."""

    def __init__(self, jit, methods=("sphere_trace", "hybrid_secant", "normal"), broken=False):
        self.capabilities = type("Caps", (), {"jit": jit, "dtypes": ("float64",)})()
        self._methods, self._broken = methods, broken

    def methods(self):
        if self._broken:
            raise RuntimeError("a plug-in's broken hook")
        return self._methods


def test_groups_are_claimed_heaviest_first_by_their_estimated_cost():
    """Compiling backends' groups before the others, a group of more methods before one of fewer;
    a backend that runs nothing of its groups last; a broken one counts as compiling everything;
    every group exactly once, and plan order among equal estimates."""
    from bench.run.sharing import heaviest_first
    from impls import Unavailable

    ids = ["eager", "jitted", "few", "none", "broken", "gone"]
    todo = plan(SUITE, ids, None, None, None)
    backends = {"eager": _Fake(False), "jitted": _Fake(True), "few": _Fake(True, ("normal",)),
                "none": _Fake(True, ()), "broken": _Fake(False, broken=True), "gone": Unavailable("gone", "not installed")}
    groups = groups_of(todo)
    order = heaviest_first(groups, todo, backends)
    assert sorted(map(tuple, order)) == sorted(map(tuple, groups))
    by = [(todo[g[0]].backend_id, todo[g[0]].case.id) for g in order]
    rank = {b: [i for i, (bid, _) in enumerate(by) if bid == b] for b in ids}
    assert max(rank["jitted"] + rank["broken"]) < min(rank["few"])  # 3 compiled methods before 1
    assert max(rank["few"]) < min(rank["eager"])  # one compiled method (×10) before 3 eager ones
    assert max(rank["eager"]) < min(rank["none"] + rank["gone"])  # nothing to run: last
    cases = [c for b, c in by if b == "jitted"]
    assert cases == sorted(cases, key=[t.case.id for t in todo].index)  # ties in plan order
