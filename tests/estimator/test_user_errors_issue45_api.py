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


def test_nanosecond_times_with_metres_per_second_are_refused(scans):
    t_ns = [1_600_000_000_000_000_000 + k * 100_000_000 for k in range(3)]  # 10 Hz in ns
    with pytest.raises(ValueError, match=r"frame period of 1e\+08 s.*look like nanoseconds.*1e-9"):
        estimate_flow(scans, config=CFG, device="cpu", times=t_ns, flow_unit="m/s")
    with pytest.raises(ValueError, match="look like milliseconds"):
        estimate_sequence(scans, CFG, device="cpu", times=[0.0, 100.0, 200.0], flow_unit="m/s")
    with pytest.raises(ValueError, match="look like milliseconds"):
        estimate_flow(scans, config=CFG, device="cpu", frame_period=100.0, flow_unit="m/s")
    # the same stamps in seconds: m/s = per-frame flow / 0.1 s; per frame, ns stamps are fine (ratios)
    per_frame = estimate_flow(scans, config=CFG, device="cpu")
    v = estimate_flow(scans, config=CFG, device="cpu", times=[k * 0.1 for k in range(3)], flow_unit="m/s")
    np.testing.assert_allclose(v, per_frame / 0.1, rtol=1e-5)
    np.testing.assert_array_equal(estimate_flow(scans, config=CFG, device="cpu", times=t_ns), per_frame)


def test_a_diverged_optimisation_says_so(scans):
    from floxels_ext import Floxels
    from floxels_ext.estimator.result import DivergedWarning

    bad = FloxelsConfig(lr=1e9, max_iters=40, patience=30)
    with pytest.warns(DivergedWarning, match=r"1 of 1 optimisation\(s\) diverged.*loss rose from .* lower lr \(lr=1e\+09\)"):
        flow = estimate_flow(scans, config=bad, device="cpu")
    assert np.all(flow == 0)  # what it returned before, silently
    with pytest.warns(DivergedWarning, match=r"2 of 2 optimisation\(s\) diverged \(frame 0, frame 2\)"):
        estimate_sequence(scans, bad, device="cpu", frames=[0, 2])
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the default lr: no warning
        res = Floxels(CFG, device="cpu").fit(scans)
    assert res.diverged is None and res.best_iter > 0
