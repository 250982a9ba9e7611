"""The re-centring's sample bounds (estimator/recentre.py ``_finite_bounds``): the fast path
(min/max of the transposed sample, finite bounds meaning a finite sample) gives exactly what
the finite rows of the sample give, whatever non-finite values the sample holds."""

import numpy as np
import pytest
import torch

from floxels_ext.estimator.recentre import SAMPLE_ROWS, _finite_bounds


def _naive(t: torch.Tensor):
    a = t[::max(1, t.shape[0] // SAMPLE_ROWS)].to(torch.float64).numpy()
    a = a[np.isfinite(a).all(axis=1)]
    return None if a.shape[0] == 0 else (a.min(axis=0), a.max(axis=0))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.float16])
@pytest.mark.parametrize("bad", [None, "nan", "inf", "-inf", "row", "all"])
def test_bounds_equal_the_finite_rows_of_the_sample(dtype, bad):
    rng = np.random.default_rng(3)
    a = rng.uniform(-40, 60, (20000, 3)) + np.array([5e3, -2e3, 10.0])
    stride = max(1, a.shape[0] // SAMPLE_ROWS)
    if bad == "all":
        a[:] = np.nan
    elif bad == "row":
        a[50 * stride] = [-1e6, 1e6, np.nan]  # a sampled row with finite extremes and one NaN: dropped
    elif bad is not None:
        # in sampled rows, one on each axis: a wrong filter moves the bounds
        for k, row in enumerate((7 * stride, 11 * stride, 300 * stride)):
            a[row, k] = float(bad)
    t = torch.from_numpy(a).to(dtype)
    got, want = _finite_bounds(t), _naive(t)
    if want is None:
        assert got is None
        return
    for g, w in zip(got, want):
        assert g.dtype == np.float64 and np.array_equal(g, w)


def test_empty_scan_has_no_bounds():
    assert _finite_bounds(torch.zeros(0, 3)) is None
