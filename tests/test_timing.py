"""The timing protocol (bench/run/timing.py: :func:`measure`) on a clock the test drives: the
first call apart, warm-up, calibration of calls per sample, the sample count between its bounds,
``sync`` after every call, accuracy-only.  No test here reads the machine's clock, so none depends
on its speed or load."""

from __future__ import annotations

import pytest

from bench.run import timing
from bench.run.timing import TimingPolicy, measure


class FakeClock:
    """``perf_counter`` for bench.run.timing: time moves only when the timed function runs, by its
    ``cost`` (seconds; the first call may cost more: ``first``)."""

    def __init__(self, cost: float, first: float | None = None):
        self.now, self.cost, self.first = 0.0, cost, first
        self.calls = self.syncs = 0
        self.events: list[str] = []

    def perf_counter(self) -> float:
        return self.now

    def run(self):
        self.now += self.first if (self.calls == 0 and self.first is not None) else self.cost
        self.calls += 1
        self.events.append("run")
        return self.calls

    def sync(self, out):
        self.syncs += 1
        self.events.append("sync")


@pytest.fixture
def clock(monkeypatch):
    def make(cost, first=None):
        c = FakeClock(cost, first)
        monkeypatch.setattr(timing.time, "perf_counter", c.perf_counter)
        return c

    return make


def test_a_fast_kernel_is_calibrated_to_the_minimum_sample_time(clock):
    """1e-4 s a call, samples of ≥ 1 ms: 16 calls a sample (8 make 0.8 ms); then samples until
    both ``min_repeats`` and ``min_time_s`` are met."""
    c = clock(1e-4)
    pol = TimingPolicy(min_repeats=3, min_time_s=0.01, min_sample_s=1e-3, warmup=1)
    t, out = measure(c.run, c.sync, pol)
    assert t.loops == 16 and t.first_call_s == pytest.approx(1e-4)
    assert out == 1  # the first call's output is the one whose accuracy is measured
    assert all(s == pytest.approx(1e-4) for s in t.samples_s)
    # 0.01 s of samples at 1.6 ms each: 7 samples (6 make 9.6 ms)
    assert len(t.samples_s) == 7
    # first + warm-up + calibration (1, 2, 4, 8, 16 calls) + 6 more samples of 16
    assert c.calls == 1 + 1 + (1 + 2 + 4 + 8 + 16) + 6 * 16
    assert c.events == ["run", "sync"] * c.calls  # every call synchronised before the clock stops


def test_a_long_first_call_without_warm_up_is_the_first_sample(clock):
    """A backend warm after its first call (warmup=0) whose call takes ≥ min_time/min_repeats: the
    first call is a sample, and the repeat count, not the time, bounds the samples."""
    c = clock(0.1)
    t, _ = measure(c.run, c.sync, TimingPolicy(min_repeats=3, min_time_s=0.05, warmup=0))
    assert t.loops == 1 and len(t.samples_s) == 3 and c.calls == 3
    assert t.median_s == pytest.approx(0.1) and t.iqr_s == pytest.approx(0.0)


def test_a_first_call_of_at_least_warm_after_s_is_the_warm_up_but_not_a_sample(clock):
    """A compiling backend (warmup=1) whose first call takes ≥ warm_after_s: no warm-up call after
    it (it was one), and the samples start with the second call (the first is still not one: a
    loaded kernel's first call can be slower than the rest, measured ×2.4 on a jax renderer)."""
    c = clock(0.1, first=0.25)
    t, _ = measure(c.run, c.sync, TimingPolicy(min_repeats=3, min_time_s=0.05, warmup=1, warm_after_s=0.05))
    assert c.calls == 1 + 3 and t.loops == 1 and len(t.samples_s) == 3
    assert t.first_call_s == pytest.approx(0.25) and all(s == pytest.approx(0.1) for s in t.samples_s)
    # a first call below warm_after_s keeps its warm-up call
    c = clock(0.1, first=0.04)
    measure(c.run, c.sync, TimingPolicy(min_repeats=3, min_time_s=0.05, warmup=1, warm_after_s=0.05))
    assert c.calls == 1 + 1 + 3


def test_a_slow_first_call_shows_as_spread_not_in_the_median(clock):
    c = clock(0.1, first=0.5)
    t, _ = measure(c.run, c.sync, TimingPolicy(min_repeats=3, min_time_s=0.05, warmup=0))
    assert t.first_call_s == pytest.approx(0.5) and t.samples_s[0] == pytest.approx(0.5)
    assert t.median_s == pytest.approx(0.1) and t.iqr_s > 0


def test_samples_stop_at_max_time_and_max_repeats(clock):
    c = clock(1.0)
    t, _ = measure(c.run, c.sync, TimingPolicy(min_repeats=50, min_time_s=0.0, max_time_s=3.5, warmup=0))
    assert len(t.samples_s) == 4  # 4 s of samples pass max_time_s = 3.5 s
    c = clock(0.01)
    t, _ = measure(c.run, c.sync, TimingPolicy(min_repeats=1, min_time_s=100.0, max_repeats=7, warmup=0,
                                               min_sample_s=0.0))
    assert len(t.samples_s) == 7


def test_accuracy_only_is_one_call(clock):
    c = clock(0.3)
    t, out = measure(c.run, c.sync, TimingPolicy(accuracy_only=True))
    assert c.calls == 1 and c.syncs == 1 and t.samples_s == [pytest.approx(0.3)] and out == 1


@pytest.mark.parametrize("field,value", [("min_repeats", 0), ("warmup", -1), ("min_time_s", float("nan")),
                                         ("max_time_s", -1.0), ("warm_after_s", -0.1)])
def test_bad_policies_name_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        TimingPolicy(**{field: value})


def test_the_unit_is_measured_right_before_and_after_the_samples_under_their_load(clock):
    """The unit runs UNIT_CALLS times after the first call and as many after the last sample, so a
    load that comes and goes between configurations is in both the samples and the unit; the
    median of its calls is ``unit_s``.  Accuracy-only runs call no unit."""
    c = clock(0.01)
    log = c.events
    unit_costs = iter([0.001, 0.003, 0.002, 0.005, 0.004, 0.006])

    def unit():
        c.now += next(unit_costs)
        log.append("unit")

    t, _ = measure(c.run, c.sync, TimingPolicy(min_repeats=3, min_time_s=0.0, min_sample_s=0.0, warmup=0), unit=unit)
    runs = [i for i, e in enumerate(log) if e == "run"]
    units = [i for i, e in enumerate(log) if e == "unit"]
    assert len(units) == 2 * timing.UNIT_CALLS
    assert units[:3] == [runs[0] + 2, runs[0] + 3, runs[0] + 4]  # after the first call (and its sync)
    assert units[3] > runs[-1]  # the other three after the last sample
    assert t.unit_s == pytest.approx(0.0035)  # median of 1, 3, 2, 5, 4, 6 ms
    assert len(t.samples_s) == 3 and t.samples_s[0] == pytest.approx(0.01)

    c2 = clock(0.01)
    t2, _ = measure(c2.run, c2.sync, TimingPolicy(accuracy_only=True), unit=lambda: pytest.fail("unit called"))
    assert t2.unit_s is None


def test_a_rows_ratio_divides_by_the_unit_measured_beside_it(monkeypatch):
    """``time_ratio_cf`` is the median time over ``Timing.unit_s``; the case's own unit (``cf_time``)
    only where the timing has none."""
    from bench.run import configuration

    monkeypatch.setattr(configuration, "measure", lambda run, sync, policy, unit=None: (
        timing.Timing(first_call_s=0.02, samples_s=[0.01, 0.01, 0.01], unit_s=0.002), run()))
    from bench.run.plan import Config
    from impls import registry
    from reference.cases import get_case

    cfg = Config(get_case("sphere.camera.64x64"), "numpy", "sphere_trace", "float64", {})
    (row,) = [r for r in configuration.run_one("r", cfg, registry.resolve("numpy"), TimingPolicy(), cf_time=1.0)
              if r["outcome"] == "ok"][:1]
    assert row["time_ratio_cf"] == pytest.approx(5.0)
