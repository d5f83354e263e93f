"""The cost floor of certified root finding (bench/studies/cost_floor.py): the oracle's greedy
sphere cover against its closed form on a plane, and no certified ray of hybrid_secant spending
fewer evaluations than the floor (it would have certified what its samples cannot show)."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest

from bench.studies import cost_floor, speed
from reference.primitives import Plane

from tests.conftest import ROOT


@pytest.mark.parametrize("sigma", [0.95, 0.5, 0.1])
def test_greedy_cover_of_a_plane_matches_the_closed_form(sigma):
    """A ray crossing the plane z = 0 at slope σ from height D: φ = σ(t* − t), each greedy sample
    leaves (1 − σ)/(1 + σ) of the distance to t* uncovered, so covering [0, t* − m] takes
    ⌈ln(t*/m) / ln((1 + σ)/(1 − σ))⌉ samples."""
    m, depth = 1e-4, 1.0
    d = np.array([[math.sqrt(1 - sigma**2), 0.0, -sigma]])
    o = np.array([[0.0, 0.0, depth]])
    t_star = depth / sigma
    got = cost_floor.greedy_cover(Plane(), o, d, np.zeros(1), np.array([t_star - m]))
    expected = math.ceil(math.log(t_star / m) / math.log((1 + sigma) / (1 - sigma)))
    assert abs(int(got[0]) - expected) <= 1, (got, expected)


@pytest.mark.parametrize("name", ["sphere", "torus∪box"])
def test_no_certified_ray_spends_less_than_the_floor(name):
    from impls import Status, registry

    scene, o, d = speed.scenes(48)[name]
    backend = registry.resolve("numpy")
    p = backend.prepare("hybrid_secant", scene, o, d, t_min=0.0, t_max=10.0)
    res = p.result(p.run())
    floor = cost_floor.floor_per_ray(scene, o, d, 10.0, min_step=1e-4)["floor"]
    certified = (res.status == Status.CONVERGED) | (res.status == Status.MISS)
    assert certified.mean() > 0.9
    below = certified & (res.evals < floor)
    assert not below.any(), (np.nonzero(below)[0][:5], res.evals[below][:5], floor[below][:5])


def test_cost_floor_command_prints_both_scenes():
    out = subprocess.run([sys.executable, "-m", "bench", "cost-floor", "--side", "24"], cwd=ROOT,
                         capture_output=True, text=True, check=True).stdout
    assert "sphere" in out and "torus∪box" in out and "floor" in out, out
    bad = subprocess.run([sys.executable, "-m", "bench", "cost-floor", "--method", "march_bisect"], cwd=ROOT,
                         capture_output=True, text=True)
    assert bad.returncode == 2 and "--method" in bad.stderr, bad.stderr
