"""The comparison logic: accuracy by tolerance, timing by factor and significance."""

from __future__ import annotations

import numpy as np

from bench.compare import timing_verdict


def test_noise_only_rerun_is_not_significant():
    rng = np.random.default_rng(1)
    a = 1e-3 * (1 + 0.05 * rng.standard_normal(30))
    b = 1e-3 * (1 + 0.05 * rng.standard_normal(30))
    assert timing_verdict(a, b)[0] == "not significant"


def test_real_slowdown_is_worse_and_small_significant_one_is_not():
    rng = np.random.default_rng(2)
    a = 1e-3 * (1 + 0.02 * rng.standard_normal(30))
    assert timing_verdict(a, 1.5 * a[::-1])[0] == "worse"
    assert timing_verdict(a, 1.05 * a[::-1])[0] == "not significant"  # below the factor
    assert timing_verdict(a, a[::-1] / 1.5)[0] == "better"


def test_few_samples_use_non_overlapping_ranges():
    a = np.array([1.0, 1.1, 0.9])
    assert timing_verdict(a, np.array([2.0, 2.1, 1.9]))[0] == "worse"
    assert timing_verdict(a, np.array([1.0, 2.1, 1.9]))[0] == "not significant"
