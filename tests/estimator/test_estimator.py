"""The Floxels estimator end to end: accuracy on a simulated scene, API contract, ablations,
sequences and bad input."""

import numpy as np
import pytest
import torch

import floxels_ext
from floxels_ext import Floxels, FloxelsConfig, estimate_flow, estimate_sequence
from floxels_ext.estimator.api import window_for
from floxels_ext.evaluation.protocol import protocol_mask
from floxels_ext.evaluation.sim import simulate_sequence

FAST = FloxelsConfig(max_iters=150, patience=100)


def _simulated(**lidar):
    """5 scans of a simulated crossing (moving cars/pedestrians, exact flow), cropped to 30 m
    with ground removed as in the paper's protocol."""
    # the box-only vehicles: on the detailed ones more gradient components are zero up to
    # rounding, whose sign decides Adam's first step (see the first-iterations test below)
    seq = simulate_sequence("crossing", num_frames=5, seed=3, vehicle_detail=False, **lidar)
    scans, gts, dyns = [], [], []
    for fr in seq.frames:
        keep = protocol_mask(fr.points, fr.pose[:3, 3], max_range=30.0, ground=fr.ground)
        scans.append(fr.points[keep])
        gts.append(fr.flow[keep])
        dyns.append(fr.dynamic[keep])
    return scans, gts, dyns


@pytest.fixture(scope="module")
def scene():
    """A sparse 32-beam lidar: fast, for API tests."""
    return _simulated(beams=32, azimuth_steps=512)


@pytest.fixture(scope="module")
def dense_scene():
    """The default 64-beam lidar (~28k points per scan after cropping), for accuracy."""
    return _simulated()


def _epe(pred, gt, mask):
    return float(np.linalg.norm(pred[mask] - gt[mask], axis=1).mean())


@pytest.mark.slow
def test_end_to_end_accuracy(dense_scene):
    scans, gts, dyns = dense_scene
    res = Floxels().fit(scans, target=2)
    gt, dyn = gts[2], dyns[2]
    assert dyn.sum() > 50, "the scene must contain moving points"
    zero = _epe(np.zeros_like(gt), gt, dyn)
    dyn_epe, static_epe = _epe(res.flow, gt, dyn), _epe(res.flow, gt, ~dyn)
    assert dyn_epe <= zero / 3, (dyn_epe, zero)
    assert static_epe < 0.05, static_epe
    assert res.losses[res.best_iter] == min(res.losses)
    # The paper's settings give this scene's numbers (the CPU solver is deterministic: the same
    # with 1 or 2 threads; measured 0.1019 / 0.0040 m). A pin, not a bound: 1/|t| time weights,
    # lr 0.1 or a 1 m voxel are *more* accurate on this scene (dynamic EPE 0.082 / 0.095 / 0.079
    # m, static 0.0040 / 0.0078 / 0.0037 m), so no upper bound can fail them; a change that moves
    # these numbers changes the method: measure it on the simulator and the real scans, say why,
    # then re-pin.
    assert dyn_epe == pytest.approx(0.1019, abs=0.003), dyn_epe
    assert static_epe == pytest.approx(0.0040, abs=0.001), static_epe
    assert res.flow.dtype == np.float32 and res.flow.shape == gt.shape


def test_result_contents(scene):
    scans, _, _ = scene
    res = Floxels(FAST).fit(scans[:3], target=1)
    assert res.num_iters == len(res.losses) <= 150
    assert res.labels.shape[0] == len(scans[1]) and res.labels.dtype == torch.int64
    grid = res.grid
    assert grid.dim() == 4 and grid.shape[0] == 3
    # the dense grid reproduces the flow through the op-level trilinear gather
    pts = torch.from_numpy(scans[1])
    again = floxels_ext.reference.ops.trilinear_gather(grid, pts, res.grid_origin, res.voxel_size)
    np.testing.assert_allclose(again.numpy(), res.flow, atol=1e-5)
    assert {"dt", "dbscan", "optimise", "total"} <= set(res.timings)


def test_tensor_in_tensor_out(scene):
    scans, _, _ = scene
    ts = [torch.from_numpy(s).double() for s in scans[:2]]
    out = estimate_flow(ts, target=0, config=FAST)
    assert isinstance(out, torch.Tensor) and out.dtype == torch.float64 and out.shape == ts[0].shape


@pytest.mark.parametrize("target", [0, 2])
def test_target_at_either_end(scene, target):
    """A window whose target is its first or last scan (support scans on one side only, time
    offsets +1, +2 or -2, -1): the flow still follows the scene (measured dynamic EPE 0.15 / 0.26
    m against 0.39 / 0.41 m for zero flow, static 0.013 / 0.014 m)."""
    scans, gts, dyns = scene
    out = estimate_flow(scans[:3], target=target, config=FAST)
    assert out.shape == scans[target].shape and np.isfinite(out).all()
    gt, dyn = gts[target], dyns[target]
    assert _epe(out, gt, dyn) < 0.7 * _epe(np.zeros_like(gt), gt, dyn)
    assert _epe(out, gt, ~dyn) < 0.02


def test_matches_reference_implementation_first_iterations(scene):
    """Same loss as the straightforward implementation at the zero initialisation and after
    the first Adam step. (Adam's first step moves every parameter by lr * sign(gradient), so
    components whose gradient is zero up to rounding make the two paths drift apart after
    that; end-to-end accuracy is compared in bench/bench_estimator.py.)"""
    from floxels_ext.reference.estimator import reference_estimate_flow

    scans, _, _ = scene
    cfg = FloxelsConfig(max_iters=2)
    res = Floxels(cfg).fit(scans, target=2)
    _, info = reference_estimate_flow(scans, target=2, config=cfg, return_info=True)
    np.testing.assert_allclose(res.losses[0], info["losses"][0], rtol=1e-6)
    np.testing.assert_allclose(res.losses[1], info["losses"][1], rtol=1e-4)


@pytest.mark.parametrize("reading", [dict(truncation_mode="clamp", truncation=0.3),
                                     dict(cluster_loss_mean="clustered")], ids=lambda r: ",".join(r))
def test_readings_match_reference_implementation(scene, reading):
    """The faithfulness readings in the estimator = in the straightforward implementation
    (first two losses, as above; the lr schedule is checked against the plain loop in
    tests/ops/test_solver.py)."""
    from floxels_ext.reference.estimator import reference_estimate_flow

    scans, _, _ = scene
    cfg = FloxelsConfig(max_iters=2, **reading)
    res = Floxels(cfg).fit(scans, target=2)
    _, info = reference_estimate_flow(scans, target=2, config=cfg, return_info=True)
    np.testing.assert_allclose(res.losses[0], info["losses"][0], rtol=1e-5)
    np.testing.assert_allclose(res.losses[1], info["losses"][1], rtol=1e-4)
    default = Floxels(FloxelsConfig(max_iters=2, truncation=cfg.truncation)).fit(scans, target=2)
    # (at the zero initialisation the cluster term is 0: compare after the first step)
    assert default.losses[:2] != pytest.approx(res.losses[:2], rel=1e-6)


@pytest.mark.parametrize("change", [dict(cluster_loss=False), dict(flow_norm_loss=False),
                                    dict(cluster_loss=False, flow_norm_loss=False), dict(voxel_size=1.0),
                                    dict(reg_scale="paper"), dict(lambda_c=0.0)])
def test_ablation_switches(scene, change):
    scans, _, _ = scene
    cfg = FAST.replace(**change)
    res = Floxels(cfg).fit(scans, target=2)
    assert np.isfinite(res.flow).all()
    if change.get("cluster_loss") is False:
        assert res.labels is None


def test_ablations_change_the_loss(scene):
    scans, _, _ = scene
    base = Floxels(FloxelsConfig(max_iters=3)).fit(scans, target=2).losses
    no_norm = Floxels(FloxelsConfig(max_iters=3, flow_norm_loss=False)).fit(scans, target=2).losses
    assert base[0] == pytest.approx(no_norm[0])  # zero flow: the norm term is 0
    assert base[1] != pytest.approx(no_norm[1])


def test_window_for():
    assert window_for(0, 10, 5) == (0, 5)
    assert window_for(5, 10, 5) == (3, 8)
    assert window_for(9, 10, 5) == (5, 10)
    assert window_for(1, 3, 5) == (0, 3)


def test_sequence_reuses_distance_transforms(scene, monkeypatch):
    scans, _, _ = scene
    import floxels_ext.estimator.group as est  # where the group's distance transforms are built

    built = []
    orig = est.build_dt
    monkeypatch.setattr(est, "build_dt", lambda p, c, *a: built.append(len(p)) or orig(p, c, *a))
    cfg = FAST.replace(num_scans=3, max_iters=20)
    flows = estimate_sequence(scans, config=cfg)
    assert len(flows) == len(scans) and all(f.shape == s.shape for f, s in zip(flows, scans))
    assert len(built) == len(scans)  # every scan's DT built exactly once
    # same result as fitting each window separately
    s, e = window_for(2, len(scans), 3)
    np.testing.assert_allclose(flows[2], estimate_flow(scans[s:e], target=2 - s, config=cfg), atol=1e-6)


def test_config_validation():
    FloxelsConfig()
    for bad in [dict(voxel_size=0), dict(lr=-1), dict(max_iters=0), dict(patience=1.5), dict(num_scans=1),
                dict(num_scans=14), dict(reg_scale="x"), dict(dt_cell=float("nan")), dict(adam_betas=(1.0, 0.9))]:
        with pytest.raises(ValueError):
            FloxelsConfig(**bad)
    c = FloxelsConfig()
    assert c.lambda_g(0) == pytest.approx(0.1) and c.lambda_g(50) == pytest.approx(0.055)
    assert c.lambda_g(100) == pytest.approx(0.01) and c.lambda_g(400) == pytest.approx(0.01)
    assert c.time_weight(-2) == pytest.approx(0.25)


def test_bad_input(scene):
    scans, _, _ = scene
    a = scans[0]
    with pytest.raises(ValueError, match="at least 2"):
        estimate_flow([a])
    with pytest.raises(IndexError, match="out of range"):
        estimate_flow([a, a], target=5)
    with pytest.raises(TypeError, match="different dtypes"):
        estimate_flow([a, a.astype(np.float64)])
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        estimate_flow([a, a[:, :2]])
    with pytest.raises(TypeError, match="config"):
        Floxels(config={"lr": 1})


def test_nan_points_dropped_with_warning(scene):
    scans, _, _ = scene
    s = [x.copy() for x in scans[:2]]
    s[0][5] = np.nan
    s[1][7, 2] = np.inf
    with pytest.warns(UserWarning, match="NaN"):
        out = estimate_flow(s, target=0, config=FAST)
    assert np.isnan(out[5]).all() and np.isfinite(np.delete(out, 5, axis=0)).all()


def test_empty_and_tiny_scans(scene):
    scans, _, _ = scene
    empty = np.zeros((0, 3), np.float32)
    assert estimate_flow([empty, scans[0]], target=0, config=FAST).shape == (0, 3)
    out = estimate_flow([scans[0], empty], target=0, config=FAST)  # support empty: no evidence
    assert out.shape == scans[0].shape and np.isfinite(out).all()
    tiny = scans[0][:3]
    assert estimate_flow([tiny, scans[1]], target=0, config=FAST).shape == (3, 3)


def test_huge_extent_is_refused_not_allocated():
    rng = np.random.default_rng(0)
    a = rng.uniform(0, 10, (100, 3)).astype(np.float32)
    far = a.copy()
    far[0] = [50_000.0, 0.0, 0.0]  # one point 50 km away: a 0.1 m grid would need ~TBs
    with pytest.raises(ValueError, match="cap"):
        estimate_flow([a, far], target=0, config=FAST)


def test_scans_far_apart_do_not_allocate_a_joint_grid():
    """Each support scan's DT covers that scan only: a support scan 20 km away costs no more
    memory than a near one and simply provides no evidence (the flow stays ~0)."""
    rng = np.random.default_rng(1)
    a = rng.uniform(0, 10, (500, 3)).astype(np.float32)
    far = a + np.float32(20_000.0)
    out = estimate_flow([a, far], target=0, config=FAST)
    assert out.shape == a.shape and np.isfinite(out).all()
    assert np.abs(out).max() < 0.5


def test_sequence_converts_each_scan_once(scene):
    """A bad scan is reported once per sequence, not once per window that contains it, and
    its dropped rows get NaN flow in its own frame."""
    import warnings

    scans, _, _ = scene
    s = [x.copy() for x in scans]
    s[1][3] = np.nan
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        flows = estimate_sequence(s, config=FAST.replace(num_scans=3, max_iters=10))
    msgs = [str(w.message) for w in caught if "NaN" in str(w.message)]
    assert len(msgs) == 1 and msgs[0].startswith("scan 1:"), msgs
    assert np.isnan(flows[1][3]).all() and np.isfinite(np.delete(flows[1], 3, axis=0)).all()


@pytest.mark.cuda
def test_sequence_pipelined_on_cuda(scene, monkeypatch):
    """On CUDA the next batch is prepared while this one is optimised: every DT is still
    built once, callbacks come in frame order, and each frame matches fitting it alone."""
    scans, _, _ = scene
    import floxels_ext.estimator.group as est  # where the group's distance transforms are built

    built = []
    orig = est.build_dt
    monkeypatch.setattr(est, "build_dt", lambda p, c, *a: built.append(len(p)) or orig(p, c, *a))
    cfg = FAST.replace(num_scans=3, max_iters=40)
    seen = []
    flows = estimate_sequence(scans, config=cfg, device="cuda", batch_size=2, callback=lambda f, r: seen.append(f))
    assert seen == list(range(len(scans))) and len(built) == len(scans)
    monkeypatch.setattr(est, "build_dt", orig)
    for f in range(len(scans)):
        s, e = window_for(f, len(scans), 3)
        alone = estimate_flow(scans[s:e], target=f - s, config=cfg, device="cuda")
        assert flows[f].shape == alone.shape and np.isfinite(flows[f]).all()
        # deterministic sums (issue 31): the same bytes as the frame fitted alone
        assert flows[f].tobytes() == alone.tobytes()


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)])
def test_sequence_error_keeps_finished_frames(scene, device):
    """A scan that fails in a later batch (here: an absurd extent) raises, but the frames
    of the batches before it are still delivered (on CUDA that batch is being optimised
    while the failing one is prepared)."""
    from floxels_ext.ops.grid import GridTooLargeError

    scans = [s.copy() for s in scene[0]]
    scans[4][0] = [1e5, 0.0, 0.0]
    seen = []
    with pytest.raises(GridTooLargeError):
        estimate_sequence(scans, config=FAST.replace(num_scans=3, max_iters=10), device=device, batch_size=2,
                          callback=lambda f, r: seen.append(f))
    assert seen == [0, 1]
