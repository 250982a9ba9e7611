"""The optional range bands of ``floxels::dt_residual`` and ``floxels::dt_evidence``
(``FloxelsConfig.range_mask``): scan k's term counts only for points whose own (unmoved)
position lies in its band (sensor x, y, horizontal r_min..r_max), never by where the motion
takes them; against the pure-PyTorch reference and a per-scan recomputation, CPU and CUDA."""

from __future__ import annotations

import pytest
import torch

import floxels_ext  # noqa: F401  (registers torch.ops.floxels.*)
from floxels_ext.ops import dt_evidence, dt_residual
from floxels_ext.reference import ops as ref
from test_dt_query import TOL, make_case, qargs, runs

ops = torch.ops.floxels
cuda = pytest.mark.cuda


def bands_for(c, seed=0):
    """(K, 4) bands that split the case's points: a sensor near the points' middle and a band
    around the median range, different per scan."""
    p = c["points"]
    g = torch.Generator().manual_seed(seed)
    K = len(c["dts"])
    mid = p[:, :2].mean(0)
    rows = []
    for _ in range(K):
        s = mid + torch.randn(2, generator=g, dtype=p.dtype) * 0.5
        r = torch.hypot(p[:, 0] - s[0], p[:, 1] - s[1])
        lo, hi = torch.quantile(r, 0.2).item(), torch.quantile(r, 0.7).item()
        rows.append([s[0].item(), s[1].item(), lo, hi])
    return torch.tensor(rows, dtype=p.dtype, device=p.device)


def inside(p, b):
    d2 = (p[:, 0] - b[0]) ** 2 + (p[:, 1] - b[1]) ** 2
    return (d2 >= b[2] ** 2) & (d2 <= b[3] ** 2)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("squared", [False, True])
def test_residual_with_bands_matches_reference_and_per_scan_sums(dtype, squared):
    c = make_case(4, 900, dtype, seed=5)
    b = bands_for(c)
    got = dt_residual(*qargs(c), c["weights"], c["cap"], squared, bands=b)
    torch.testing.assert_close(got, ref.dt_residual(*qargs(c), c["weights"], c["cap"], squared, b), **TOL[dtype])
    assert torch.equal(ops.dt_residual(*qargs(c), c["weights"], c["cap"], squared, b), got)
    # = the sum of the one-scan residuals over the scans whose band holds the point
    want = torch.zeros_like(got)
    p, m, dts, o, sp, t = qargs(c)
    for k in range(4):
        one = dt_residual(p, m, [dts[k]], o[3 * k:3 * k + 3], sp, [t[k]], [c["weights"][k]], c["cap"], squared)
        want += torch.where(inside(p, b[k]), one, torch.zeros_like(one))
    torch.testing.assert_close(got, want, **TOL[dtype])
    assert 0.1 < inside(p, b[0]).float().mean() < 0.9  # the bands do split the points


def test_band_holding_every_point_changes_nothing():
    c = make_case(3, 500, torch.float64, seed=2)
    wide = torch.tensor([[0.0, 0.0, 0.0, 1e6]] * 3, dtype=torch.float64)
    a = dt_residual(*qargs(c), c["weights"], c["cap"], False)
    assert torch.equal(dt_residual(*qargs(c), c["weights"], c["cap"], False, bands=wide), a)
    cells = torch.arange(500) // 10
    e0 = dt_evidence(c["points"], c["motion"], None, cells, c["dts"], c["origins"], c["spacing"], c["time_offsets"],
                     c["weights"], c["cap"], 0.02, 0.05)
    e1 = dt_evidence(c["points"], c["motion"], None, cells, c["dts"], c["origins"], c["spacing"], c["time_offsets"],
                     c["weights"], c["cap"], 0.02, 0.05, bands=wide)
    for x, y in zip(e0, e1):
        assert torch.equal(x, y)


def test_band_decides_by_the_point_not_the_query():
    """A motion that carries a point out of a scan's band does not drop the scan's term."""
    c = make_case(1, 300, torch.float64, seed=4)
    p = c["points"]
    b = torch.tensor([[p[:, 0].mean().item(), p[:, 1].mean().item(), 0.0, 1e6]], dtype=torch.float64)
    far = torch.full_like(c["motion"], 1e3)  # every query far outside the band (and the DT)
    r = dt_residual(p, far, c["dts"], c["origins"], c["spacing"], c["time_offsets"], c["weights"], c["cap"],
                    bands=b)
    torch.testing.assert_close(r, torch.full_like(r, c["weights"][0] * c["cap"]))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_evidence_with_bands_matches_reference(dtype):
    n = 2500
    c = make_case(4, n, dtype, seed=21)
    b = bands_for(c, seed=1)
    lab, cells = runs(n, 2)
    a = (c["points"], c["motion"], lab, cells, c["dts"], c["origins"], c["spacing"], c["time_offsets"],
         c["weights"], c["cap"], 0.02, 0.05)
    got, want = dt_evidence(*a, bands=b), ref.dt_evidence(*a, bands=b)
    for k in (0, 2, 3):
        torch.testing.assert_close(got[k], want[k], **TOL[dtype])
    clear = (want[0] - torch.clamp(want[3] * 0.05, min=0.02)).abs() > 1e-4
    assert torch.equal(got[1][clear], want[1][clear])
    plain = dt_evidence(*a)
    assert not torch.equal(plain[3], got[3])  # the bands changed the residuals


def test_bands_bad_input():
    c = make_case(2, 50, torch.float64)
    args = (*qargs(c), c["weights"], c["cap"], False)
    with pytest.raises(ValueError, match=r"bands must have shape \(2, 4\)"):
        dt_residual(*args, bands=torch.zeros(3, 4, dtype=torch.float64))
    with pytest.raises(ValueError, match="bands must be finite"):
        dt_residual(*args, bands=torch.tensor([[0.0, 0.0, 0.0, float("nan")]] * 2, dtype=torch.float64))
    with pytest.raises(TypeError):
        dt_residual(*args, bands=[[0.0, 0.0, 0.0, 1.0]] * 2)
    with pytest.raises(RuntimeError, match=r"bands must have shape"):  # the raw op checks too
        ops.dt_residual(*args, torch.zeros(2, 3, dtype=torch.float64))
    with pytest.raises(RuntimeError, match="bands"):
        ops.dt_residual(*args, torch.zeros(2, 4, dtype=torch.float32))


def test_opcheck_with_bands():
    c = make_case(2, 40, torch.float64)
    b = torch.tensor([[0.0, 0.0, 0.5, 3.0], [0.1, 0.0, 0.0, 2.0]], dtype=torch.float64)
    cells = torch.arange(40) // 4
    torch.library.opcheck(ops.dt_residual, (*qargs(c), c["weights"], 1.0, True, b))
    torch.library.opcheck(ops.dt_evidence, (c["points"], c["motion"], None, cells, c["dts"], c["origins"],
                                            c["spacing"], c["time_offsets"], c["weights"], 1.0, 0.02, 0.05, b))


@cuda
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cuda_bands_match_cpu_and_repeat_bytes(dtype):
    n = 30000
    c = make_case(5, n, dtype, seed=33)
    b = bands_for(c, seed=3)
    lab, cells = runs(n, 4)
    d = {k: (v.cuda() if isinstance(v, torch.Tensor) else [x.cuda() for x in v] if k == "dts" else v)
         for k, v in c.items()}
    bd = b.cuda()
    tol = TOL[dtype] if dtype == torch.float64 else dict(rtol=1e-5, atol=1e-5)
    for sq in (False, True):
        g1 = ops.dt_residual(*qargs(d), d["weights"], d["cap"], sq, bd)
        assert torch.equal(g1, ops.dt_residual(*qargs(d), d["weights"], d["cap"], sq, bd))
        torch.testing.assert_close(g1.cpu(), ops.dt_residual(*qargs(c), c["weights"], c["cap"], sq, b), **tol)
    tail = (d["dts"], d["origins"], d["spacing"], d["time_offsets"], d["weights"], d["cap"], 0.02, 0.05, bd)
    e1 = ops.dt_evidence(d["points"], d["motion"], lab.cuda(), cells.cuda(), *tail)
    e2 = ops.dt_evidence(d["points"], d["motion"], lab.cuda(), cells.cuda(), *tail)
    for x, y in zip(e1, e2):
        assert torch.equal(x, y)
    ec = ops.dt_evidence(c["points"], c["motion"], lab, cells, c["dts"], c["origins"], c["spacing"],
                         c["time_offsets"], c["weights"], c["cap"], 0.02, 0.05, b)
    for k in (0, 2, 3):
        torch.testing.assert_close(e1[k].cpu(), ec[k], **tol)
