"""NSFP and FastNSF baselines: losses vs brute-force references, rigid-translation recovery,
configs, registry entries and bad input."""

import math
import warnings

import numpy as np
import pytest
import torch

from floxels_ext import methods
from floxels_ext.reference import ops as reference
from floxels_ext.baselines import (CoordinateMLP, FastNSFConfig, NSFPConfig, estimate_flow_fastnsf,
                                   estimate_flow_nsfp, fit_fastnsf, fit_nsfp, nearest_neighbors,
                                   nn_distances, truncated_chamfer)
from floxels_ext.baselines.fastnsf import target_distance_transform
from floxels_ext.baselines.registry import pair_for_frame
from floxels_ext.ops import ops_ns

SHIFT = np.array([0.4, -0.25, 0.1], np.float32)


def cloud(n, seed=0):
    rng = np.random.default_rng(seed)
    return (rng.uniform(-1, 1, (n, 3)) * [4, 4, 1]).astype(np.float32)


# ----------------------------------------------------------------------------- Chamfer
def brute_chamfer(x, y, trunc, squared):
    d = np.sqrt(((x[:, None, :].astype(np.float64) - y[None].astype(np.float64)) ** 2).sum(-1))
    if squared:
        d = d**2
    dx, dy = d.min(1), d.min(0)
    return np.where(dx < trunc, dx, 0).mean() + np.where(dy < trunc, dy, 0).mean()


@pytest.mark.parametrize("n,m", [(1, 1), (1, 9), (37, 53), (200, 150)])
@pytest.mark.parametrize("trunc,squared", [(2.0, True), (0.5, True), (0.7, False), (math.inf, False)])
def test_truncated_chamfer_matches_brute_force(n, m, trunc, squared):
    rng = np.random.default_rng(n * 1000 + m)
    x = rng.uniform(-2, 2, (n, 3)).astype(np.float32)
    y = rng.uniform(-2, 2, (m, 3)).astype(np.float32)
    got = truncated_chamfer(torch.from_numpy(x), torch.from_numpy(y), trunc, squared).item()
    assert got == pytest.approx(brute_chamfer(x, y, trunc, squared), rel=1e-5, abs=1e-6)


def test_chamfer_gradient_matches_dense_autograd():
    rng = np.random.default_rng(3)
    x = torch.tensor(rng.uniform(-2, 2, (60, 3)), requires_grad=True)
    y = torch.tensor(rng.uniform(-2, 2, (45, 3)), requires_grad=True)
    truncated_chamfer(x, y, 1.0).backward()
    x2, y2 = x.detach().clone().requires_grad_(), y.detach().clone().requires_grad_()
    d = ((x2[:, None] - y2[None]) ** 2).sum(-1)  # dense squared distances, autograd through min
    dx, dy = d.min(1).values, d.min(0).values
    (torch.where(dx < 1.0, dx, 0 * dx).mean() + torch.where(dy < 1.0, dy, 0 * dy).mean()).backward()
    torch.testing.assert_close(x.grad, x2.grad)
    torch.testing.assert_close(y.grad, y2.grad)


def test_nearest_neighbors_chunking_is_exact():
    rng = np.random.default_rng(4)
    x = torch.tensor(rng.uniform(-30, 30, (300, 3)), dtype=torch.float32)
    y = torch.tensor(rng.uniform(-30, 30, (170, 3)), dtype=torch.float32)
    full = torch.cdist(x.double(), y.double()).argmin(1)
    for chunk in (0, 1, 7, 170, 1 << 24):
        assert torch.equal(nearest_neighbors(x, y, chunk), full)
    assert torch.allclose(nn_distances(x, y, squared=False), torch.cdist(x.double(), y.double()).min(1).values.float())


def test_chamfer_bad_input():
    x = torch.zeros(3, 3)
    with pytest.raises(ValueError, match="empty"):
        truncated_chamfer(x, torch.zeros(0, 3))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        truncated_chamfer(x, torch.zeros(4, 2))
    with pytest.raises(ValueError, match="truncation"):
        truncated_chamfer(x, x, truncation=0.0)


# ----------------------------------------------------------------------------- DT loss
def _dt_setup(seed=5, n=120, m=150):
    rng = np.random.default_rng(seed)
    src = torch.tensor(rng.uniform(-2, 2, (n, 3)) * [1, 1, 0.5], dtype=torch.float32)
    tgt = torch.tensor(rng.uniform(-2, 2, (m, 3)) * [1, 1, 0.5], dtype=torch.float32)
    flow = torch.tensor(rng.normal(0, 0.3, (n, 3)), dtype=torch.float32)
    return src, tgt, flow


@pytest.mark.parametrize("trunc", [math.inf, 0.3])
def test_fastnsf_dt_loss_matches_reference(trunc):
    cfg = FastNSFConfig(truncation=trunc)
    src, tgt, flow = _dt_setup()
    dt, origin = target_distance_transform(src, tgt, cfg)
    # the DT itself: exact EDT (pure-PyTorch reference) of the snapped target points
    occ = reference.points_to_occupancy(tgt, origin, cfg.dt_cell, dt.shape)
    torch.testing.assert_close(dt, reference.edt(occ, cfg.dt_cell))
    f1 = flow.clone().requires_grad_()
    loss = ops_ns.dt_loss(src, f1, [dt], origin, cfg.dt_cell, [1.0], [1.0], trunc)
    loss.backward()
    f2 = flow.double().requires_grad_()
    ref = reference.dt_loss(src.double(), f2, [dt.double()], origin, cfg.dt_cell, [1.0], [1.0], trunc)
    ref.backward()
    assert loss.item() == pytest.approx(ref.item(), rel=1e-5, abs=1e-6)
    torch.testing.assert_close(f1.grad, f2.grad.float(), rtol=1e-4, atol=1e-6)


def test_fastnsf_dt_close_to_brute_force_nearest_distance():
    """The sampled DT approximates the exact distance to the next scan: per point within the
    snapping (sqrt(3)/2 h) plus interpolation (sqrt(3) h) error bound."""
    cfg = FastNSFConfig()
    src, tgt, flow = _dt_setup(seed=6)
    dt, origin = target_distance_transform(src, tgt, cfg)
    q = src + flow
    interp = reference.trilinear_gather(dt[None], q, origin, cfg.dt_cell)[:, 0]
    exact = torch.cdist(q.double(), tgt.double()).min(1).values.float()
    h = cfg.dt_cell
    assert (interp - exact).abs().max() <= 1.5 * math.sqrt(3) * h + 1e-4
    loss = ops_ns.dt_loss(src, flow, [dt], origin, h, [1.0], [1.0], math.inf)
    assert loss.item() == pytest.approx(interp.mean().item(), rel=1e-5)
    assert abs(loss.item() - exact.mean().item()) < h


# ----------------------------------------------------------------------------- translation recovery
def test_nsfp_recovers_rigid_translation():
    src = cloud(400)
    res = fit_nsfp(src, src + SHIFT, NSFPConfig(max_iters=300))
    assert res.flow.shape == (400, 3) and res.flow.dtype == np.float32
    epe = np.linalg.norm(res.flow - SHIFT, axis=1).mean()
    assert epe < 0.02, epe
    assert res.num_iters == len(res.losses) and 0 <= res.best_iter < res.num_iters
    assert res.losses[res.best_iter] == min(res.losses)


def test_fastnsf_recovers_rigid_translation():
    src = cloud(400)
    res = fit_fastnsf(src, src + SHIFT, FastNSFConfig(max_iters=200))
    epe = np.linalg.norm(res.flow - SHIFT, axis=1).mean()
    assert epe < 0.05, epe  # the DT's 0.1 m lattice limits the precision
    assert set(res.timings) >= {"dt", "optimise", "total"}


def test_nsfp_without_backward_flow_and_plain_distances():
    src = cloud(300, seed=2)
    cfg = NSFPConfig(max_iters=250, backward_flow=False, chamfer_squared=False, chamfer_truncation=1.5)
    flow = estimate_flow_nsfp(src, src + SHIFT, cfg)
    assert np.linalg.norm(flow - SHIFT, axis=1).mean() < 0.05


def test_early_stopping_and_max_iters():
    src = cloud(100)
    res = fit_fastnsf(src, src + SHIFT, FastNSFConfig(max_iters=40, early_stopping=False))
    assert res.num_iters == 40
    res = fit_fastnsf(src, src + SHIFT, FastNSFConfig(max_iters=5000, patience=5, min_delta=10.0))
    assert res.num_iters == 6  # the first iteration improves on +inf, then 5 without improvement


def test_deterministic_and_tensor_io():
    src = cloud(120)
    a = estimate_flow_fastnsf(src, src + SHIFT, FastNSFConfig(max_iters=20))
    b = estimate_flow_fastnsf(src, src + SHIFT, FastNSFConfig(max_iters=20))
    np.testing.assert_array_equal(a, b)
    t = torch.from_numpy(src).double()
    out = estimate_flow_fastnsf(t, t + torch.from_numpy(SHIFT).double(), FastNSFConfig(max_iters=20))
    assert isinstance(out, torch.Tensor) and out.dtype == torch.float64 and out.shape == (120, 3)
    np.testing.assert_allclose(out.numpy(), a, atol=1e-5)


def test_mlp_structure_and_seed():
    net = CoordinateMLP(num_layers=8, width=128)
    linears = [m for m in net if isinstance(m, torch.nn.Linear)]
    assert len(linears) == 9 and linears[0].in_features == 3 and linears[-1].out_features == 3
    state = torch.get_rng_state()
    a, b, c = CoordinateMLP(seed=3), CoordinateMLP(seed=3), CoordinateMLP(seed=4)
    assert torch.equal(torch.get_rng_state(), state)  # the caller's RNG is untouched
    assert torch.equal(a[0].weight, b[0].weight) and not torch.equal(a[0].weight, c[0].weight)
    x = CoordinateMLP(init="xavier")
    assert torch.count_nonzero(x[0].bias) == 0
    with pytest.raises(ValueError, match="activation"):
        CoordinateMLP(activation="gelu")


# ----------------------------------------------------------------------------- configs
@pytest.mark.parametrize("cls,kw,match", [
    (NSFPConfig, {"lr": 0.0}, "lr"),
    (NSFPConfig, {"lr": float("nan")}, "lr"),
    (NSFPConfig, {"num_layers": 0}, "num_layers"),
    (NSFPConfig, {"max_iters": True}, "max_iters"),
    (NSFPConfig, {"patience": -1}, "patience"),
    (NSFPConfig, {"min_delta": -1e-4}, "min_delta"),
    (NSFPConfig, {"activation": "gelu"}, "activation"),
    (NSFPConfig, {"adam_betas": (1.0, 0.9)}, "adam_betas"),
    (NSFPConfig, {"chamfer_truncation": 0.0}, "chamfer_truncation"),
    (NSFPConfig, {"early_stopping": 1}, "early_stopping"),
    (NSFPConfig, {"max_points": -5}, "max_points"),
    (FastNSFConfig, {"dt_cell": 0.0}, "dt_cell"),
    (FastNSFConfig, {"dt_padding": -1.0}, "dt_padding"),
    (FastNSFConfig, {"truncation": float("nan")}, "truncation"),
    (FastNSFConfig, {"init": "he"}, "init"),
])
def test_config_rejects_bad_values(cls, kw, match):
    with pytest.raises(ValueError, match=match):
        cls(**kw)


def test_config_defaults_follow_the_paper():
    n, f = NSFPConfig(), FastNSFConfig()
    for c in (n, f):
        assert (c.num_layers, c.hidden_units, c.activation) == (8, 128, "relu")
        assert (c.patience, c.min_delta, c.max_iters) == (100, 1e-4, 5000)
    # NSFP's code: weight decay 1e-4 in both parameter groups (they override the optimiser's 0)
    assert n.weight_decay == 1e-4 and f.weight_decay == 0.0
    assert n.lr == 0.008 and f.lr == 0.001 and f.dt_cell == 0.1 and n.backward_flow
    assert n.replace(lr=0.0008).lr == 0.0008
    with pytest.raises(ValueError):
        n.replace(lr=-1.0)


# ----------------------------------------------------------------------------- registry
def _sequence(n_scans=3, n=150):
    base = cloud(n, seed=9)
    return [base + k * SHIFT for k in range(n_scans)]


@pytest.mark.parametrize("name", ["nsfp", "fastnsf"])
def test_registry_entries(name):
    assert {"floxels", "nsfp", "fastnsf"} <= set(methods.available_methods())
    scans = _sequence()
    got = {}
    methods.get_method(name).estimate_sequence(scans, [0, 2], "cpu", {"max_iters": 150},
                                               lambda f, flow: got.__setitem__(f, flow))
    assert sorted(got) == [0, 2]
    for f in (0, 2):  # frame 2 (last) is estimated towards scan 1 and negated
        assert got[f].shape == (150, 3)
        assert np.linalg.norm(got[f] - SHIFT, axis=1).mean() < 0.06, (f, got[f].mean(0))
    with pytest.raises(ValueError, match="unknown option"):
        methods.get_method(name).estimate_sequence(scans, [0], "cpu", {"voxel_size": 0.5}, lambda f, fl: None)
    with pytest.raises(ValueError, match="lr"):
        methods.get_method(name).estimate_sequence(scans, [0], "cpu", {"lr": -1}, lambda f, fl: None)
    with pytest.raises(IndexError):
        methods.get_method(name).estimate_sequence(scans, [3], "cpu", {}, lambda f, fl: None)


def test_pair_for_frame():
    assert pair_for_frame(0, 3) == (1, 1.0)
    assert pair_for_frame(2, 3) == (1, -1.0)
    with pytest.raises(ValueError, match="at least 2"):
        pair_for_frame(0, 1)


# ----------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("fn,cfg", [(estimate_flow_nsfp, NSFPConfig(max_iters=5)),
                                    (estimate_flow_fastnsf, FastNSFConfig(max_iters=5))])
def test_bad_inputs(fn, cfg):
    src = cloud(50)
    with pytest.raises(ValueError, match="source"):
        fn(src[:, :2], src, cfg)
    with pytest.raises(ValueError, match="target"):
        fn(src, src[None], cfg)
    with pytest.raises(TypeError, match="float"):
        fn(src.astype(np.int32), src, cfg)
    with pytest.raises(TypeError, match="mix"):
        fn(src, torch.from_numpy(src), cfg)
    with pytest.raises(TypeError, match="config"):
        fn(src, src, NSFPConfig() if isinstance(cfg, FastNSFConfig) else FastNSFConfig())
    # empty source -> empty flow; empty target -> zero flow with a warning
    assert fn(src[:0], src, cfg).shape == (0, 3)
    with pytest.warns(UserWarning, match="no \\(finite\\) points"):
        out = fn(src, src[:0], cfg)
    np.testing.assert_array_equal(out, np.zeros_like(src))
    # NaN rows: dropped with a warning, NaN flow in their rows, finite elsewhere
    bad = src.copy()
    bad[[3, 7]] = np.nan
    with pytest.warns(UserWarning, match="NaN"):
        out = fn(bad, src + SHIFT, cfg)
    assert out.shape == (50, 3)
    assert np.isnan(out[[3, 7]]).all() and np.isfinite(np.delete(out, [3, 7], axis=0)).all()


def test_single_point_source():
    src = cloud(30)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = estimate_flow_nsfp(src[:1], src + SHIFT, NSFPConfig(max_iters=10))
    assert out.shape == (1, 3) and np.isfinite(out).all()


def test_max_points_subsampling_still_predicts_every_point():
    src = cloud(300)
    res = fit_fastnsf(src, src + SHIFT, FastNSFConfig(max_iters=30, max_points=120))
    assert res.flow.shape == (300, 3) and np.isfinite(res.flow).all()
    # a cap above the cloud size changes nothing
    a = estimate_flow_fastnsf(src, src + SHIFT, FastNSFConfig(max_iters=30, max_points=300))
    b = estimate_flow_fastnsf(src, src + SHIFT, FastNSFConfig(max_iters=30))
    np.testing.assert_array_equal(a, b)


# ----------------------------------------------------------------------------- nearest_neighbor op
def test_nearest_neighbor_op_matches_reference_cpu():
    from floxels_ext.ops import nearest_neighbor

    rng = np.random.default_rng(5)
    x = torch.tensor(rng.uniform(-30, 30, (257, 3)), dtype=torch.float32)
    y = torch.tensor(rng.uniform(-30, 30, (190, 3)), dtype=torch.float32)
    y[7] = y[3]  # an exact tie: the lowest index wins, like argmin
    x[0] = y[3]
    got = nearest_neighbor(x, y)
    assert torch.equal(got, reference.nearest_neighbor(x, y))
    assert got[0].item() == 3
    assert torch.equal(got, nearest_neighbors(x, y))  # the chunked cdist path agrees
    assert torch.equal(nearest_neighbor(x.double(), y.double()), reference.nearest_neighbor(x.double(), y.double()))
    assert nearest_neighbor(torch.zeros(0, 3), y).shape == (0,)
    with pytest.raises(ValueError, match="empty"):
        nearest_neighbor(x, torch.zeros(0, 3))
    # the raw op maps NaN distances to +inf (a diverged query still gets a valid index)
    xn = x.clone()
    xn[1, 0] = float("nan")
    got = ops_ns.nearest_neighbor(xn, y)
    assert 0 <= got[1].item() < y.shape[0]


def test_optimise_device_bookkeeping_matches_early_stopping_replay():
    """The device-side stop/best tracking gives what EarlyStopping gives on the same losses."""
    from floxels_ext.estimator.early_stopping import EarlyStopping

    src = cloud(200)
    cfg = NSFPConfig(max_iters=400, patience=15, min_delta=1e-3)
    res = fit_nsfp(src, src + SHIFT, cfg)
    stopper = EarlyStopping(cfg.patience, cfg.min_delta)
    stops = [stopper.update(v, i)[1] for i, v in enumerate(res.losses)]
    assert res.best_iter == stopper.best_iter
    assert not any(stops[:-1]) and (stops[-1] or len(res.losses) == cfg.max_iters)


# ----------------------------------------------------------------------------- CUDA
@pytest.mark.cuda
def test_cuda_matches_cpu():
    rng = np.random.default_rng(11)
    x = torch.tensor(rng.uniform(-20, 20, (700, 3)), dtype=torch.float32)
    y = torch.tensor(rng.uniform(-20, 20, (500, 3)), dtype=torch.float32)
    assert torch.equal(nearest_neighbors(x.cuda(), y.cuda(), 1000).cpu(), nearest_neighbors(x, y))
    torch.testing.assert_close(truncated_chamfer(x.cuda(), y.cuda(), 50.0).cpu(), truncated_chamfer(x, y, 50.0),
                               rtol=1e-5, atol=1e-6)
    src = cloud(300)
    for fn, cfg in ((fit_nsfp, NSFPConfig(max_iters=150)), (fit_fastnsf, FastNSFConfig(max_iters=150))):
        a = fn(src, src + SHIFT, cfg, device="cpu").flow
        b = fn(src, src + SHIFT, cfg, device="cuda").flow
        assert np.linalg.norm(b - SHIFT, axis=1).mean() < 0.05
        assert np.abs(a - b).mean() < 0.03


# ----------------------------------------------------------------------------- bench/compare.py
def test_compare_bench_smoke(tmp_path):
    import importlib.util
    import json
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "bench" / "compare.py"
    spec = importlib.util.spec_from_file_location("bench_compare", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    parts = []
    for scene, timing in (("crossing", []), ("urban", ["--repeat", "2", "--warmup", "full"])):
        # one row split over two parts, then merged
        out = tmp_path / f"c_{scene}.json"
        assert mod.main(["--quick", "--frames", "1", "--max-points", "150", "--iters-scale", "0.0001",
                         "--scenes", scene, "--methods", "floxels", "nsfp", "fastnsf", "--ablations", "loss",
                         "--json", str(out), *timing]) == 0
        parts.append(str(out))
    d = json.loads(Path(parts[0]).read_text())
    assert [r["key"] for r in d["rows"]][:3] == ["floxels", "nsfp", "fastnsf"]
    assert sum(r["group"] == "loss" for r in d["rows"]) == 4
    assert {"dynamic_epe", "static_acc10", "mean_dynamic_normalized_epe"} <= set(d["rows"][0]["metrics"])
    assert len(d["rows"][0]["seconds_runs"]["crossing"]) == 1  # --quick: one timed run
    runs = json.loads(Path(parts[1]).read_text())["rows"][0]["seconds_runs"]["urban"]
    assert len(runs) == 2 and json.loads(Path(parts[1]).read_text())["rows"][0]["seconds"]["urban"] == \
        pytest.approx(sum(runs) / 2)  # the median of two
    merged = tmp_path / "m.json"
    assert mod.main(["--merge", *parts, "--json", str(merged), "--md", str(tmp_path / "m.md")]) == 0
    rows = json.loads(merged.read_text())["rows"]
    assert len(rows) == 7 and all(set(r["frames"]) == {"crossing", "urban"} for r in rows)
    assert "| Floxels (5 scans) |" in (tmp_path / "m.md").read_text()


@pytest.mark.cuda
def test_nearest_neighbor_cuda_matches_reference():
    from floxels_ext.ops import nearest_neighbor

    rng = np.random.default_rng(12)
    for n, m in ((5, 7), (300, 20000), (9000, 3000)):  # one segment; many segments (atomic keys)
        x = torch.tensor(rng.uniform(-40, 40, (n, 3)), dtype=torch.float32)
        y = torch.tensor(rng.uniform(-40, 40, (m, 3)), dtype=torch.float32)
        y[-1] = y[0]
        x[0] = y[0]
        want = torch.cat([reference.nearest_neighbor(x[s:s + 500], y) for s in range(0, n, 500)])
        got = nearest_neighbor(x.cuda(), y.cuda()).cpu()
        assert torch.equal(got, want)
        assert torch.equal(nearest_neighbor(x.cuda().double(), y.cuda().double()).cpu(),
                           nearest_neighbor(x.double(), y.double()))
    assert torch.equal(nearest_neighbors(x.cuda(), y.cuda()).cpu(), want)
