"""Issue 31 end to end: estimate_flow, estimate_sequence (batched and unbatched) and
fit_many give the same bytes run after run on CUDA, and a frame the same bytes whatever else
is batched with it. Needs a GPU (device tool)."""

import numpy as np
import pytest

from floxels_ext import Floxels, FloxelsConfig, estimate_flow, estimate_sequence
from floxels_ext.estimator.api import window_for

from test_estimator import _simulated

pytestmark = pytest.mark.cuda
CFG = FloxelsConfig(max_iters=80, patience=40, num_scans=3)


@pytest.fixture(scope="module")
def scans():
    return _simulated(beams=32, azimuth_steps=512)[0]


def _same(a, b):
    a, b = (x.cpu().numpy() if hasattr(x, "cpu") else np.asarray(x) for x in (a, b))
    assert a.shape == b.shape and a.dtype == b.dtype
    assert a.tobytes() == b.tobytes(), f"max |diff| {np.nanmax(np.abs(a - b))}"


def test_estimate_flow_twice(scans):
    _same(estimate_flow(scans, config=CFG, device="cuda"), estimate_flow(scans, config=CFG, device="cuda"))


@pytest.mark.parametrize("batch_size", [1, 2, 5])
def test_estimate_sequence_twice_and_any_batch(scans, batch_size):
    """Twice the same bytes; and batched like unbatched (each frame alone, window_for)."""
    a = estimate_sequence(scans, config=CFG, device="cuda", batch_size=batch_size)
    b = estimate_sequence(scans, config=CFG, device="cuda", batch_size=batch_size)
    for f in range(len(scans)):
        _same(a[f], b[f])
        s, e = window_for(f, len(scans), CFG.num_scans)
        _same(a[f], estimate_flow(scans[s:e], target=f - s, config=CFG, device="cuda"))


def test_fit_many_twice_and_alone(scans):
    windows = [(scans[0:3], 1), (scans[1:4], 1), (scans[2:5], 1)]
    model = Floxels(CFG, device="cuda")
    a, b = model.fit_many(windows), model.fit_many(windows)
    for k in range(len(windows)):
        _same(a[k].flow, b[k].flow)
        _same(a[k].flow, model.fit(*windows[k]).flow)
