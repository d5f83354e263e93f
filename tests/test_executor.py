"""The runner has one execution loop whatever the executor (bench/run/executor.py): an executor
that finishes configurations out of order still gives rows in plan order, one that is
interrupted leaves the run incomplete with the reason and resumable, and the in-process
executor records the machine and task seconds on every row."""

from __future__ import annotations

import json

from bench.run import runner
from bench.run.configuration import base_row
from bench.run.executor import InProcessExecutor, Interrupted
from bench.run.results import read_results
from bench.run.suites import Suite
from bench.run.timing import TimingPolicy
from impls import registry

SUITE = Suite("t", "sphere.camera.64x64", ("float64",), {"sphere_trace": [{"tol": 1e-4}, {"tol": 1e-8}, {"tol": 1e-12}]},
              methods=("sphere_trace",))
POLICY = TimingPolicy(accuracy_only=True)


class Reversed:
    """Yields every configuration, last first, without running it (one skipped row each); stops
    with :class:`Interrupted` after ``stop_after`` when given."""

    def __init__(self, stop_after: int | None = None):
        self.stop_after, self.seen = stop_after, []

    def execute(self, run_id, todo, backends, policy, ref_options, budget_s, deadline, on_start=None):
        for n, j in enumerate(reversed(range(len(todo)))):
            if self.stop_after is not None and n == self.stop_after:
                raise Interrupted("the fake cluster went away")
            self.seen.append(j)
            cfg = todo[j]
            yield j, [{**base_row(run_id, cfg, backends[cfg.backend_id]), "outcome": "skipped",
                       "reason": f"fake {j}"}], False

    def retime_rounds(self, *args):
        raise AssertionError("accuracy-only: no rounds")

    def closed_form_samples(self):
        return {}

    def env_record(self, previous=None):
        return {"fake.executor": "yes"}


def test_rows_come_in_plan_order_whatever_the_executors_order(tmp_path):
    backends = {"numpy": registry.resolve("numpy")}
    ex = Reversed()
    df = runner.run(SUITE, backends, tmp_path, policy=POLICY, executor=ex)
    n = len(runner.plan(SUITE, ["numpy"], None, None, None))
    assert ex.seen == list(reversed(range(n))) and n == 3
    assert list(df["reason"]) == [f"fake {j}" for j in range(n)]
    env = json.loads((tmp_path / "environment.json").read_text())
    assert env["complete"] == "true" and env["fake.executor"] == "yes"


def test_an_interrupted_executor_leaves_an_incomplete_resumable_run(tmp_path):
    backends = {"numpy": registry.resolve("numpy")}
    runner.run(SUITE, backends, tmp_path, policy=POLICY, executor=Reversed(stop_after=1))
    env = json.loads((tmp_path / "environment.json").read_text())
    assert env["complete"] == "false" and "the fake cluster went away" in env["incomplete_reason"]
    assert "2 configurations not run" in env["incomplete_reason"]
    assert len(read_results(tmp_path)) == 1
    ex = Reversed()
    df = runner.run(SUITE, backends, tmp_path, policy=POLICY, resume=True, executor=ex)
    assert sorted(ex.seen) == [0, 1] and len(df) == 3  # only what was missing ran
    assert json.loads((tmp_path / "environment.json").read_text())["complete"] == "true"


def test_in_process_rows_record_the_machine_and_task_seconds(tmp_path):
    backends = {"numpy": registry.resolve("numpy")}
    df = runner.run(SUITE, backends, tmp_path, policy=POLICY, executor=InProcessExecutor("machine-x"))
    assert set(df["machine_key"]) == {"machine-x"} and (df["task_s"] > 0).all()
    assert set(df["outcome"]) == {"ok"}
