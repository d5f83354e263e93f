"""The catalog sweep's projection (:mod:`bench.studies.sweep_projection`): its sample and its
arithmetic, on a results table made up here (a real sample run takes minutes)."""

from __future__ import annotations

import json
from collections import Counter

import pandas as pd
import pytest

from bench.studies import sweep_projection as sp
from reference import catalog


def test_the_sample_is_every_kth_case_of_the_sorted_catalog():
    ids = sorted(c.id for c in catalog())
    a, b = sp.sample_ids(8, 0), sp.sample_ids(8, 4)
    assert a == ids[0::8] and b == ids[4::8]
    assert not set(a) & set(b) and len(a) == -(-len(ids) // 8)
    for every, offset in ((0, 0), (8, 8), (8, -1)):
        with pytest.raises(ValueError, match="every"):
            sp.sample_ids(every, offset)


def _row(case, backend, method, quantity, outcome, task_s):
    return dict(case_id=case, backend=backend, dtype="float64", method=method, knob="k=1", quantity=quantity,
                outcome=outcome, task_s=task_s)


def test_projection_is_each_backends_mean_per_configuration_run_times_its_count(tmp_path):
    rows = [_row("c1", "numpy", "m", "depth", "ok", 2.0), _row("c1", "numpy", "m", "normal", "ok", 2.0),  # one config
            _row("c2", "numpy", "m", "depth", "ok", 4.0),
            _row("c1", "jax:cpu", "m", "depth", "ok", 10.0),
            _row("c2", "jax:cpu", "m", "depth", "skipped", 0.0)]  # planned, not run: not in the mean
    pd.DataFrame(rows).to_csv(tmp_path / "results.csv", index=False)
    (tmp_path / "environment.json").write_text(json.dumps({"elapsed_s": "20.0"}))
    rates, wall, planned, task = sp.sample_rates(tmp_path)
    assert rates == {"numpy": 3.0, "jax:cpu": 10.0} and (wall, planned, task) == (20.0, 4, 16.0)
    text = sp.project([tmp_path], Counter({"numpy": 100, "jax:cpu": 10, "warp:cpu": 5}), planned=400)
    # 100·3 + 10·10 + 400 planned × (20 − 16)/4 s of harness per planned configuration
    assert "projected sweep: 800 s (0.22 h)" in text
    assert "harness 1000.0 ms per planned configuration" in text
    assert "no sample configuration ran on warp:cpu" in text
