"""Issue 45 through the API (``estimate_flow`` / ``estimate_sequence``): tensors that require a
gradient, nanosecond ``times=`` with ``flow_unit="m/s"``, an optimisation that diverged, an
empty preset name."""

import numpy as np
import pytest
import torch

from floxels_ext import FloxelsConfig, estimate_flow, estimate_sequence


@pytest.fixture(scope="module")
def scans():
    from floxels_ext.evaluation.sim import simulate_sequence

    seq = simulate_sequence("crossing", 3, 0, beams=16, azimuth_steps=360)
    return [f.points.astype(np.float64) for f in seq.frames]


CFG = FloxelsConfig(max_iters=12)


@pytest.mark.parametrize("shift", [0.0, 4e5])  # near the origin, and re-centred (UTM-like)
def test_tensors_that_require_grad_are_read_as_data(scans, shift):
    # regression: recentre.py called numpy() on them ("Can't call numpy() on Tensor that requires grad")
    plain = [torch.tensor(s + shift) for s in scans]
    grad = [t.clone().requires_grad_(True) for t in plain]
    flow = estimate_flow(grad, config=CFG, device="cpu")
    assert isinstance(flow, torch.Tensor) and not flow.requires_grad and flow.dtype == torch.float64
    torch.testing.assert_close(flow, estimate_flow(plain, config=CFG, device="cpu"), rtol=0, atol=0)
    flows = estimate_sequence(grad, CFG, device="cpu", frames=[1])
    assert not flows[0].requires_grad and all(t.grad is None for t in grad)
