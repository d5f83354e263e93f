"""pytest-benchmark micro-benchmarks of the hot kernels (skipped by default: pyproject adds
``--benchmark-skip``).  Run them with

    python -m pytest tests/benchmarks --benchmark-only [--benchmark-compare]

Each benchmark times one synchronised call on the quick camera case (64×64 rays, float64): the
closed-form ray–sphere intersection (the run's unit of time), one field evaluation φ(x) per
backend, and every method each backend implements at its default knobs.
"""

from __future__ import annotations

import numpy as np
import pytest

from impls import METHODS, registry
from reference import get_case
from reference.quadric import ray_sphere_roots
from tests.conftest import BACKEND_IDS

CASE = "sphere.camera.64x64"


def test_closed_form_ray_sphere(benchmark):
    case = get_case(CASE)
    t0, _ = benchmark(ray_sphere_roots, case.origins, case.directions, (0.0, 0.0, 0.0), 1.0)
    assert np.isfinite(t0).sum() > 0


@pytest.fixture(params=BACKEND_IDS)
def backend(request):
    b = registry.resolve(request.param)
    if isinstance(b, registry.Unavailable):
        pytest.skip(b.reason)
    return b


def test_field_evaluation(benchmark, backend):
    case = get_case(CASE)
    x = backend.asarray(case.origins + 2.0 * case.directions, "float64")

    def run():
        out = case.scene.value(x, backend.xp)
        backend.synchronize(out)
        return out

    out = benchmark(run)
    assert backend.to_numpy(out).shape == (case.n_rays,)


@pytest.mark.parametrize("method", sorted(METHODS))
def test_method_default_knobs(benchmark, backend, method):
    if method not in backend.methods():
        pytest.skip(f"{backend.id} does not implement {method}")
    case = get_case(CASE)
    spec = METHODS[method]
    if spec.skip_reason(case.scene):
        pytest.skip(spec.skip_reason(case.scene))
    extra = {"t_hit": case.exact_t} if spec.needs_t_hit else {}
    prep = backend.prepare(method, case.scene, case.origins, case.directions, dtype="float64",
                           t_min=case.t_min, t_max=case.t_max, **extra)
    prep.run()  # compile / warm up outside the timing

    def run():
        out = prep.run()
        backend.synchronize(out)
        return out

    res = prep.result(benchmark(run))
    assert res.t.shape == (case.n_rays,)
