"""The torch backend's namespace (impls.torch.backend.xp_fast): torch's own kernels for a few hot
functions, with array_api_compat's meaning (dtype rules, values, NaN and inf) on every argument
kind the library passes, and array_api_compat itself for anything else."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
xp_compat = pytest.importorskip("array_api_compat.torch")

from impls.torch.backend import TorchBackend, xp_fast  # noqa: E402

SPECIAL = [1.0, np.inf, -np.inf, np.nan, 0.0, -0.0, 1e308, -5e-324, 2.5]


def _same(a, b):
    """Equal dtype, shape and values, NaN where the other has NaN."""
    assert a.dtype == b.dtype and a.shape == b.shape
    if a.is_floating_point():
        assert torch.equal(torch.isnan(a), torch.isnan(b))
        a, b = (torch.nan_to_num(v, nan=0.0, posinf=float("inf"), neginf=float("-inf")) for v in (a, b))
    assert torch.equal(a, b)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_where_clip_isfinite_match_array_api_compat(dtype):
    a = torch.tensor(SPECIAL, dtype=dtype)
    b = torch.linspace(-3, 3, len(SPECIAL), dtype=dtype)
    m = torch.tensor([True, False] * 4 + [True])
    i32 = torch.arange(len(SPECIAL), dtype=torch.int32)
    cases = [(a, b), (1.5, a), (a, -2.0), (i32, 3), (7, i32), (a, float("inf")), (2, a), (a, 3),
             (True, m), (m, False), (1.5, i32), (a.double(), b.float()), (m, i32)]
    for x1, x2 in cases:
        _same(xp_fast.where(m, x1, x2), xp_compat.where(m, x1, x2))
    _same(xp_fast.isfinite(a), xp_compat.isfinite(a))
    _same(xp_fast.isfinite(i32), xp_compat.isfinite(i32))
    _same(xp_fast.clip(a, -1.0, 2.0), xp_compat.clip(a, -1.0, 2.0))
    _same(xp_fast.clip(i32, 1, 4), xp_compat.clip(i32, 1, 4))


def test_take_along_axis_and_delegation():
    x = torch.arange(12.0, dtype=torch.float64).reshape(3, 4)
    idx = torch.tensor([[3], [0], [2]])
    _same(xp_fast.take_along_axis(x, idx, axis=1), xp_compat.take_along_axis(x, idx, axis=1))
    assert xp_fast.float64 is torch.float64 and xp_fast.concat is xp_compat.concat
    assert TorchBackend.xp is xp_fast


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_maximum_minimum_match_array_api_compat_to_the_sign_of_zero(dtype):
    """With a Python scalar on either side (the cached 0-d tensor), two tensors, or what falls back
    (another dtype, NaN, an integer tensor): array_api_compat's dtype, values, NaN and signed zeros."""
    a = torch.tensor(SPECIAL, dtype=dtype)
    i64 = torch.tensor([0, -3, 7])
    other = a.double() if dtype == torch.float32 else a.float()
    scalars = [0.0, -0.0, 1.0, -2.5, 3, 0, float("inf"), float("-inf"), float("nan"), True]
    cases = [(a, s) for s in scalars] + [(s, a) for s in scalars] + [(a, a.flip(0)), (a, other), (i64, 2), (2.5, i64)]
    for x1, x2 in cases:
        for fast, compat in ((xp_fast.maximum, xp_compat.maximum), (xp_fast.minimum, xp_compat.minimum)):
            got, want = fast(x1, x2), compat(x1, x2)
            _same(got, want)
            if got.is_floating_point():
                assert torch.equal(torch.signbit(got), torch.signbit(want)), (x1, x2, got, want)
