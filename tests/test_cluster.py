"""Sweeps on a dask LocalCluster of 2 worker processes (bench/run/cluster.py): the same rows as one
process, nothing lost or duplicated when a worker dies or the client is killed, a configuration
that kills its worker every time is a failed row with the reason."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

pytest.importorskip("distributed")

from bench.run import runner  # noqa: E402
from bench.report import spread  # noqa: E402
from bench.run.results import KEY, read_results  # noqa: E402
from bench.run.suites import get_suite  # noqa: E402
from bench.run.timing import Timeout, TimingPolicy, time_limit  # noqa: E402
from impls import registry  # noqa: E402
from tests.conftest import HANG_GUARD_S  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
ACCURACY = TimingPolicy(min_repeats=1, min_time_s=0.0, timeout_s=60.0, accuracy_only=True)
#: what must be identical between a run in one process and on the cluster
ACCURACY_COLUMNS = ["case_version", "outcome", "reason", "unit", "status_counts", "error_max", "error_p99",
                    "error_median", "error_max_finite", "error_rel_max", "error_ulps_max", "n_checked", "n_declined",
                    "n_false_hit", "n_false_miss", "evals_per_ray", "evals_p99", "evals_max", "iterations_max",
                    "error_iterate_median", "reference_error_bound"]
KILLER = "tests.cluster_backends:KillAlways"
KILL_ONCE = "tests.cluster_backends:KillOnce"


@pytest.fixture(scope="module")
def markers(tmp_path_factory):
    d = tmp_path_factory.mktemp("markers")
    os.environ["ISOBENCH_TEST_MARKERS"] = str(d)  # before the workers start: they inherit it
    return d


@pytest.fixture(scope="module")
def cluster(markers):
    from bench.run.cluster import ClusterExecutor

    # one worker death is forgiven, the second makes a KilledWorker (dask's default is 3; fewer
    # restarts keep the test short)
    with ClusterExecutor(local=2, threads=1, allowed_failures=1, accuracy_only=True, calibrate=50) as ex:
        yield ex


def _backends(*ids):
    return {b: registry.resolve(b) for b in ids}


def _keys(df):
    return df[KEY].astype(str).apply(tuple, axis=1)


def _configs(df):
    return set(map(tuple, df[runner.CONFIG_KEY].astype(str).itertuples(index=False, name=None)))


@pytest.mark.slow  # a dask cluster of 2 worker processes
def test_rows_identical_to_one_process_and_integrals_shared(tmp_path, cluster):
    # render methods with the costly rendering integral on: one integral per case and sharpness,
    # computed once on the cluster and read by the configurations that need it
    suite = dataclasses.replace(get_suite("quick"), expensive_references=True)
    kw = dict(case_pattern="sphere.surface", policy=ACCURACY,
              methods=["sphere_trace", "hybrid_secant", "normal", "curvature", "dt_implicit", "render_surface",
                       "volume_nerf_uniform"])
    one = runner.run(suite, _backends("numpy"), tmp_path / "one", **kw)
    many = runner.run(suite, _backends("numpy"), tmp_path / "many", executor=cluster, **kw)
    assert not many.duplicated(KEY).any() and len(many) == len(one)
    a, b = one.set_index(KEY).sort_index(), many.set_index(KEY).sort_index()
    assert list(a.index) == list(b.index)
    pd.testing.assert_frame_equal(a[ACCURACY_COLUMNS], b[ACCURACY_COLUMNS], check_dtype=False)
    # written in plan order, as one process writes them
    assert list(_keys(one)) == list(_keys(many))
    integral = many[(many["quantity"] == "color_vs_integral") & (many["method"] == "volume_nerf_uniform")]
    assert (integral["outcome"] == "ok").all() and len(integral) >= 3
    env = json.loads((tmp_path / "many" / "environment.json").read_text())
    # one reference task per case and sharpness (the quick sweep varies n_samples only), read by
    # every configuration checked against it; its seconds reported once, as in one process
    assert len(json.loads(env["cluster.reference_task_s"])) == 1
    assert (pd.to_numeric(integral["reference_s"]) > 0).sum() == 1
    # every row records the worker that measured it; both workers took part
    assert many["worker"].str.startswith("tcp://").all() and many["worker"].nunique() == 2
    assert many["machine_key"].nunique() == 1 and (pd.to_numeric(many["task_s"]) > 0).all()
    assert env["complete"] == "true" and env["cluster"] == "local:2"
    s = spread.summary(many, env)
    assert s["processes that ran configurations"] == 2 and s["configurations"] == len(_configs(many))


@pytest.mark.slow  # a dask cluster of 2 worker processes
def test_a_worker_killed_mid_task_loses_and_duplicates_nothing(tmp_path, cluster, markers):
    kw = dict(case_pattern="sphere.far.1e3,sphere.surface", methods=["sphere_trace"], policy=ACCURACY)
    df = runner.run(get_suite("quick"), _backends(KILL_ONCE), tmp_path / "run", executor=cluster, **kw)
    ref = runner.run(get_suite("quick"), _backends("numpy"), tmp_path / "ref", **kw)
    assert (markers / "killed-once").exists(), "no worker was killed: the test did not test anything"
    env = json.loads((tmp_path / "run" / "environment.json").read_text())
    assert int(env["cluster.workers_died"]) == 1
    assert not df.duplicated(KEY).any()
    assert _configs(df) == {(c, KILL_ONCE, d, m, k) for c, _, d, m, k in _configs(ref)}
    assert (df["outcome"] == "ok").all() and env["complete"] == "true"
    on_disk = read_results(tmp_path / "run")
    assert len(on_disk) == len(df) and not on_disk.duplicated(KEY).any()
    # the rerun measured what one process measures
    a = ref.set_index(["case_id", "method", "knob", "quantity"]).sort_index()
    b = df.set_index(["case_id", "method", "knob", "quantity"]).sort_index()
    pd.testing.assert_frame_equal(a[ACCURACY_COLUMNS], b[ACCURACY_COLUMNS], check_dtype=False)


@pytest.mark.slow  # a dask cluster of 2 worker processes
def test_a_dying_task_never_shares_a_worker_with_another(tmp_path, cluster):
    """No worker is ever given a task while it runs another, even as a configuration kills its
    worker: dask's own retry sent the dead worker's task at once to the worker still running a
    configuration, to wait there, and a worker's death is charged to every task it holds, running
    or waiting (a configuration that kills its worker failed a numpy row so, on a loaded 2-core
    machine).  The executor retries it itself, on a free worker thread (cluster_jobs.died_again).
    The scheduler's assignments are polled every 10 ms through a run whose configurations each
    take 0.4 s (``Slow``) beside one that kills its worker twice."""
    shared, done = [], threading.Event()

    def poll():
        while not done.is_set():
            shared.extend((w, keys) for w, keys in cluster.client.processing().items() if len(keys) > 1)
            time.sleep(0.01)

    watcher = threading.Thread(target=poll, daemon=True)
    watcher.start()
    try:
        df = runner.run(get_suite("quick"), _backends("tests.cluster_backends:Slow", KILLER), tmp_path / "run",
                        executor=cluster, case_pattern="sphere.far.1e3", methods=["sphere_trace"], policy=ACCURACY)
    finally:
        done.set()
        watcher.join()
    assert not shared, f"a task waited on a worker behind another: {shared[:3]}"
    bad = df["outcome"] != "ok"
    assert bad.sum() == 1 and df.loc[bad, "backend"].tolist() == [KILLER], df.loc[bad, ["backend", "reason"]]


@pytest.mark.slow  # a dask cluster of 2 worker processes
def test_a_configuration_that_always_kills_its_worker_is_a_failed_row(tmp_path, cluster):
    df = runner.run(get_suite("quick"), _backends("numpy", KILLER), tmp_path / "run", executor=cluster,
                    case_pattern="sphere.far.1e3", methods=["sphere_trace"], policy=ACCURACY)
    assert not df.duplicated(KEY).any()
    killer = df[df["backend"] == KILLER]
    bad = killer[killer["knob"].str.contains("tol=1e-12")]
    assert len(bad) == 1 and bad["outcome"].iloc[0] == "failed"
    assert bad["reason"].iloc[0].startswith("KilledWorker: its worker process died 2 times")
    assert (killer.drop(bad.index)["outcome"] == "ok").all() and len(killer) >= 3
    assert (df[df["backend"] == "numpy"]["outcome"] == "ok").all()
    assert _configs(df[df["backend"] == "numpy"]) == {(c, "numpy", d, m, k) for c, _, d, m, k in _configs(killer)}
    env = json.loads((tmp_path / "run" / "environment.json").read_text())
    assert env["complete"] == "true" and int(env["cluster.workers_died"]) == 2
    # both killed workers come back, however long their nannies take on a loaded machine: dask's
    # LocalCluster closed for good a worker not back within 15 s (lost-worker-timeout), on CI a
    # third "death" and a worker fewer for the rest of the run
    from dask import config
    from dask.utils import parse_timedelta

    assert parse_timedelta(config.get("distributed.deploy.lost-worker-timeout")) >= 3600
    cluster.client.wait_for_workers(2, timeout=HANG_GUARD_S)
    assert len(cluster.cluster.workers) == 2


@pytest.mark.slow  # a dask cluster of 2 worker processes
def test_resume_after_the_client_is_killed(tmp_path):
    out = tmp_path / "run"
    args = [sys.executable, "-m", "bench", "run", "--cluster", "local:2", "--backend", "tests.cluster_backends:Slow",
            "--case", "sphere.far.1e3,sphere.surface,torus.far.1e3", "--method", "sphere_trace,hybrid_secant",
            "--accuracy-only", "--no-claims", "--no-progress", "--out", str(out)]
    env = {**os.environ, "ISOBENCH_TEST_SLOW_S": "0.4"}
    # its own session: killing the group kills the client and the workers it started, as a
    # killed CI job would
    p = subprocess.Popen(args, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                         start_new_session=True)
    deadline = time.monotonic() + HANG_GUARD_S
    partial = None
    while time.monotonic() < deadline and p.poll() is None:
        try:
            partial = read_results(out)
            if len(partial) >= 3:
                break
        except (FileNotFoundError, ValueError):
            pass
        time.sleep(0.05)
    os.killpg(p.pid, signal.SIGKILL)
    p.wait(timeout=30)
    assert p.returncode == -signal.SIGKILL, "the run finished before it could be killed; slow it down"
    partial = read_results(out)
    first = json.loads((out / "environment.json").read_text())
    assert first["complete"] == "false" and 0 < len(partial)

    q = subprocess.run(args + ["--resume"], cwd=ROOT, env=env, capture_output=True, text=True, timeout=HANG_GUARD_S)
    assert q.returncode == 0, q.stdout[-3000:] + q.stderr[-3000:]
    full = read_results(out)
    env2 = json.loads((out / "environment.json").read_text())
    assert env2["complete"] == "true" and env2["resumed"] == "1" and env2["run_id"] == first["run_id"]
    assert not full.duplicated(KEY).any() and len(full) > len(partial)
    # rows name the plug-in by its id, "Slow"; the workers resolve it by its spec
    plan = runner.plan(get_suite("quick"), ["Slow"], "sphere.far.1e3,sphere.surface,torus.far.1e3",
                       ["sphere_trace", "hybrid_secant"], None)
    assert {tuple(map(str, c.key)) for c in plan} == _configs(full)
    # the rows finished before the kill are kept as they were (same worker process, not redone)
    merged = partial.merge(full, on=KEY, suffixes=("_a", "_b"))
    assert len(merged) == len(partial) and (merged["worker_pid_a"] == merged["worker_pid_b"]).all()
    assert set(full["worker_pid"]) - set(partial["worker_pid"]), "the resumed session ran nothing itself"


def test_time_limit_stops_a_runaway_loop_in_a_worker_thread():
    """dask runs tasks in threads, where no signal arrives: the watchdog raises Timeout there,
    also into code that swallows exceptions, and never after the block is left."""
    got = {}

    def work():
        t0 = time.monotonic()
        try:
            with time_limit(0.2, "--timeout"):
                while True:
                    try:
                        sum(range(100))
                    except Exception:  # noqa: BLE001 - what a careless backend does
                        pass
        except Timeout as exc:
            got["timeout"] = (str(exc), time.monotonic() - t0)
        for i in range(300):  # limits left in time, or passing during set-up or clean-up
            try:
                with time_limit(1e-4 * (i % 5 + 1)):
                    sum(range(i))
            except Timeout:
                pass
        t1 = time.monotonic()
        while time.monotonic() - t1 < 1.2:  # nothing lands after the blocks were left
            sum(range(100))
        got["after"] = True

    th = threading.Thread(target=work)
    th.start()
    th.join(timeout=HANG_GUARD_S)
    assert got.get("after"), got
    msg, took = got["timeout"]
    # the loop never ends by itself: that it ended at all is the limit's doing; the bound only
    # rules out a limit that fired on some later occasion (the watchdog re-fires every second)
    assert "time limit of 0.2 s (--timeout)" in msg and took < 60


def test_projection_model():
    # greedy list scheduling: 4 tasks of 1 s on 2 workers take 2 s; one long task bounds it
    assert spread.list_schedule(np.ones(4), 2) == 2.0
    assert spread.list_schedule(np.array([3.0, 1, 1, 1]), 2) == 3.0
    rows = pd.DataFrame({"case_id": [f"c{i}" for i in range(8)], "backend": "numpy", "dtype": "float64",
                         "method": "m", "knob": "", "task_s": 1.0, "worker": "", "machine_key": "k",
                         "reason": ""})
    env = {"cluster.overhead_s": json.dumps({"mean": 0.5}), "cluster.central_s": "0.25",
           "cluster.critical_path_s": "2.5", "cluster.reference_task_s": "[]"}
    proj, notes = spread.project(rows, env, workers=(1, 2, 64))
    # 8 tasks of 1 + 0.5 s: 12 s on 1 worker, 6 s on 2; on 64 the central bound (8 × 0.25) and
    # the critical path (2.5 s) take over
    assert list(proj["projected wall s"]) == [12.0, 6.0, 2.5]
    assert list(proj["limited by"]) == ["workers", "workers", "critical path"]
    assert any("measured in this run" in n for n in notes)
    # a list schedule within 1 % of the critical path is limited by it, not by the workers:
    # one 100 s task, then eight of 1 s, on 8 workers end at 100.5 s: the longest task plus o
    long = pd.concat([rows.iloc[:1].assign(case_id="long", task_s=100.0), rows], ignore_index=True)
    proj, _ = spread.project(long, {**env, "cluster.critical_path_s": "100"}, workers=(1, 8))
    assert list(proj["projected wall s"]) == [112.5, 100.5]
    assert list(proj["limited by"]) == ["workers", "critical path"]
    proj, notes = spread.project(rows, {}, workers=(2,))
    assert proj["projected wall s"].iloc[0] == 4.0 and any("lower bound" in n for n in notes)


def test_cluster_flags_are_checked():
    from bench.commands import main
    from bench.run.cluster import parse_local

    assert parse_local("local:3") == 3
    for bad in ("local:0", "local:x", "tcp://a:1"):
        with pytest.raises(ValueError, match="--cluster"):
            parse_local(bad)
    assert main(["run", "--cluster", "local:2", "--scheduler", "tcp://127.0.0.1:1", "--case", "sphere.far.1e3",
                 "--out", "/nonexistent/x"]) == 2
