"""The raw ops' contract for non-finite and extreme input (docs/ops.md, "Non-finite and extreme input"): op against
reference on NaN / +inf / -inf / +-1e30 coordinates, on CPU and (marked cuda) on CUDA against
the CPU op; bad host scalars (origin, spacing, ...) raise naming the argument."""

from __future__ import annotations

import math

import pytest
import torch

import floxels_ext  # noqa: F401  (registers torch.ops.floxels.*)
from floxels_ext.reference import ops as ref

OPS = torch.ops.floxels
DTYPES = [torch.float32, torch.float64]
# non-finite values, then huge finite ones (must clamp like outside points, never overflow an index)
NONFINITE = [math.nan, math.inf, -math.inf]
BAD = NONFINITE + [1e30, -1e30]
DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)]

SHAPE = (4, 5, 6)  # Z, Y, X
ORIGIN = [-0.5, 0.25, -1.0]
SPACING = 0.5


def _points(n, dtype, bad, seed, shape=SHAPE, origin=ORIGIN, spacing=SPACING):
    """n points in and around the lattice; every third row gets `bad` in one coordinate
    (axis cycling), and row 1, if present, in all three."""
    g = torch.Generator().manual_seed(seed)
    Z, Y, X = shape
    ext = torch.tensor([X - 1, Y - 1, Z - 1], dtype=torch.float64) * spacing
    p = (torch.rand(n, 3, generator=g, dtype=torch.float64) * 1.4 - 0.2) * ext + torch.tensor(origin)
    p = p.to(dtype)
    for i in range(0, n, 3):
        p[i, (i // 3) % 3] = bad
    if n > 1:
        p[1] = bad
    return p


def _finite(p):
    return torch.isfinite(p).all(dim=1)


def _close(a, b, dtype):
    tol = dict(rtol=1e-4, atol=1e-4) if dtype == torch.float32 else dict(rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(a, b, equal_nan=True, **tol)


def _dev(device):
    if device == "cuda" and not torch.cuda.is_available():
        pytest.skip("needs a CUDA device")
    return device


# --- trilinear gather / scatter -----------------------------------------------------------

@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("bad", BAD)
def test_trilinear_gather(device, dtype, bad):
    d = _dev(device)
    g = torch.Generator().manual_seed(1)
    grid = torch.randn(2, *SHAPE, generator=g, dtype=dtype)
    pts = _points(50, dtype, bad, seed=2)
    out = OPS.trilinear_gather(grid.to(d), pts.to(d), ORIGIN, SPACING).cpu()
    _close(out, ref.trilinear_gather(grid, pts, ORIGIN, SPACING), dtype)
    # NaN rows exactly at the non-finite points, finite elsewhere (huge finite ones clamp)
    assert torch.equal(torch.isnan(out).all(dim=1), ~_finite(pts))
    assert torch.isfinite(out[_finite(pts)]).all()
    if math.isfinite(bad):  # a clamped point reads the border: the value of a clamped copy
        big = torch.tensor(ORIGIN, dtype=torch.float64) + torch.tensor(SHAPE[::-1], dtype=torch.float64) * SPACING
        clamped = torch.minimum(torch.maximum(pts.double(), torch.tensor(ORIGIN) - 1), big + 1).to(dtype)
        _close(out, OPS.trilinear_gather(grid, clamped, ORIGIN, SPACING), dtype)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("bad", BAD)
def test_trilinear_gather_gradients(device, dtype, bad):
    """Masked loss: the NaN rows are constants, zero points-gradient rows, no grid gradient."""
    d = _dev(device)
    g = torch.Generator().manual_seed(3)
    grid0 = torch.randn(3, *SHAPE, generator=g, dtype=dtype)
    pts0 = _points(40, dtype, bad, seed=4)
    w = torch.randn(40, 3, generator=g, dtype=dtype)

    def grads(fn, dev):
        grid = grid0.to(dev).requires_grad_()
        pts = pts0.to(dev).requires_grad_()
        out = fn(grid, pts, ORIGIN, SPACING)
        loss = (torch.where(torch.isnan(out), torch.zeros_like(out), out) * w.to(dev)).sum()
        loss.backward()
        return grid.grad.cpu(), pts.grad.cpu()

    gg, gp = grads(OPS.trilinear_gather, d)
    rg, rp = grads(ref.trilinear_gather, "cpu")
    _close(gg, rg, dtype)
    _close(gp, rp, dtype)
    assert torch.isfinite(gg).all() and torch.isfinite(gp).all()
    assert (gp[~_finite(pts0)] == 0).all()


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("bad", BAD)
@pytest.mark.parametrize("n", [30, 6000])  # 6000: the CPU's sorted multi-thread path
def test_trilinear_scatter(device, dtype, bad, n):
    d = _dev(device)
    g = torch.Generator().manual_seed(5)
    pts = _points(n, dtype, bad, seed=6)
    vals = torch.randn(n, 2, generator=g, dtype=dtype)
    if not math.isfinite(bad):
        vals[1] = math.nan  # a non-finite point's values are not read either
    out = OPS.trilinear_scatter(vals.to(d), pts.to(d), ORIGIN, SPACING, list(SHAPE)).cpu()
    _close(out, ref.trilinear_scatter(vals, pts, ORIGIN, SPACING, list(SHAPE)), dtype)
    assert torch.isfinite(out).all()  # nothing written to sample (0, 0, 0) or anywhere else
    if not math.isfinite(bad):  # ignored: the same as scattering only the finite rows
        ok = _finite(pts)
        _close(out, OPS.trilinear_scatter(vals[ok], pts[ok], ORIGIN, SPACING, list(SHAPE)), dtype)


# --- occupancy and the distance-transform loss --------------------------------------------

@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("bad", BAD)
def test_points_to_occupancy(device, dtype, bad):
    d = _dev(device)
    pts = _points(60, dtype, bad, seed=7)
    occ = OPS.points_to_occupancy(pts.to(d), ORIGIN, SPACING, list(SHAPE)).cpu()
    assert torch.equal(occ, ref.points_to_occupancy(pts, ORIGIN, SPACING, list(SHAPE)))
    # non-finite and huge points are ignored: only the rows without a bad value count
    keep = ~(pts.double() == bad).any(dim=1) if math.isfinite(bad) else _finite(pts)
    assert torch.equal(occ, OPS.points_to_occupancy(pts[keep], ORIGIN, SPACING, list(SHAPE)))


def _dt_case(dtype, seed=8):
    g = torch.Generator().manual_seed(seed)
    dts = [3.0 * torch.rand(*SHAPE, generator=g), ref.edt(torch.rand(3, 4, 5, generator=g) < 0.2, SPACING)]
    origins = ORIGIN + [0.0, -0.5, 0.5]
    flow = (torch.randn(60, 3, generator=g, dtype=torch.float64) * 0.3).to(dtype)
    return dts, origins, flow


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("bad", BAD)
@pytest.mark.parametrize("where", ["points", "flow"])
def test_dt_loss(device, dtype, bad, where):
    d = _dev(device)
    dts, origins, flow = _dt_case(dtype)
    pts = _points(60, dtype, 0.0, seed=9)  # bad = 0.0: all finite
    if where == "points":
        pts = _points(60, dtype, bad, seed=9)
    else:
        flow[::4, 1] = bad
    args = (dts, origins, SPACING, [1.0, -2.0], [1.0, 0.25], 2.5)
    loss, grad = OPS.dt_loss_fwd_bwd(pts.to(d), flow.to(d), [x.to(d) for x in args[0]], *args[1:])
    loss, grad = loss.cpu(), grad.cpu()
    f = flow.clone().requires_grad_()
    rloss = ref.dt_loss(pts, f, *args)
    rloss.backward()
    _close(loss, rloss.detach(), dtype)
    _close(grad, f.grad, dtype)
    assert math.isnan(loss.item()) == (not math.isfinite(bad))
    assert torch.isfinite(grad).all()
    ok = _finite(pts) & _finite(flow)
    assert (grad[~ok] == 0).all()
    # the loss op and its backward agree with the fused pass
    _close(OPS.dt_loss(pts.to(d), flow.to(d), [x.to(d) for x in args[0]], *args[1:]).cpu(), loss, dtype)
    gb = OPS.dt_loss_backward(torch.tensor(2.0, dtype=dtype, device=d), pts.to(d), flow.to(d),
                              [x.to(d) for x in args[0]], *args[1:]).cpu()
    _close(gb, 2 * grad, dtype)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
def test_dt_loss_query_overflow_clamps(device, dtype):
    """Finite point and flow whose query p + t f overflows to +-inf: clamps like any outside
    query (finite loss), it is not a non-finite row."""
    d = _dev(device)
    dts, origins, flow = _dt_case(dtype)
    pts = _points(60, dtype, 0.0, seed=10)
    big = torch.finfo(dtype).max
    flow[3] = torch.tensor([big, -big, big / 2], dtype=dtype)
    args = (dts, origins, SPACING, [4.0, -4.0], [1.0, 1.0], 2.5)
    loss, grad = OPS.dt_loss_fwd_bwd(pts.to(d), flow.to(d), [x.to(d) for x in dts], *args[1:])
    f = flow.clone().requires_grad_()
    rloss = ref.dt_loss(pts, f, *args)
    rloss.backward()
    assert math.isfinite(loss.item())
    _close(loss.cpu(), rloss.detach(), dtype)
    _close(grad.cpu(), f.grad, dtype)


# --- cluster reductions and compact corners: non-finite values propagate ------------------

@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("bad", NONFINITE)
def test_cluster_ops_propagate(device, dtype, bad):
    d = _dev(device)
    g = torch.Generator().manual_seed(11)
    flow = torch.randn(40, 3, generator=g, dtype=dtype)
    labels = torch.randint(-1, 4, (40,), generator=g)
    labels[5] = 2
    flow[5, 0] = bad
    mean = OPS.cluster_mean(flow.to(d), labels.to(d), 4).cpu()
    _close(mean, ref.cluster_mean(flow, labels, 4), dtype)
    assert not torch.isfinite(mean[2]).all() and torch.isfinite(mean[[0, 1, 3]]).all()
    loss = OPS.cluster_consistency_loss(flow.to(d), labels.to(d), 4).cpu()
    _close(loss, ref.cluster_consistency_loss(flow, labels, 4), dtype)
    assert math.isnan(loss.item())
    fl, _ = OPS.cluster_consistency_fwd_bwd(flow.to(d), labels.to(d), 4)
    assert math.isnan(fl.item())
    # a noise point's non-finite flow is not part of any cluster: no effect
    flow2 = flow.clone()
    flow2[5, 0] = 0.0
    labels2 = labels.clone()
    labels2[7] = -1
    flow2[7] = bad
    ok_loss = OPS.cluster_consistency_loss(flow2.to(d), labels2.to(d), 4).cpu()
    assert math.isfinite(ok_loss.item())
    _close(ok_loss, ref.cluster_consistency_loss(flow2, labels2, 4), dtype)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("bad", NONFINITE)
def test_corner_ops_propagate(device, dtype, bad):
    d = _dev(device)
    g = torch.Generator().manual_seed(12)
    params = torch.randn(10, 3, generator=g, dtype=dtype)
    idx = torch.randint(0, 10, (20, 8), generator=g, dtype=torch.int32)
    w = torch.rand(20, 8, generator=g, dtype=dtype)
    vals = torch.randn(20, 3, generator=g, dtype=dtype)
    params[4, 1] = bad
    w[6, 2] = bad
    vals[9, 0] = bad
    _close(OPS.corner_gather(params.to(d), idx.to(d), w.to(d)).cpu(), ref.corner_gather(params, idx, w), dtype)
    _close(OPS.corner_scatter(vals.to(d), idx.to(d), w.to(d), 10).cpu(), ref.corner_scatter(vals, idx, w, 10),
           dtype)


# --- ops that refuse non-finite points ----------------------------------------------------

@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("bad", BAD)
def test_dbscan(device, dtype, bad):
    d = _dev(device)
    g = torch.Generator().manual_seed(13)
    pts = (torch.rand(80, 3, generator=g, dtype=torch.float64) * 3).to(dtype)
    pts[17, 2] = bad
    if math.isfinite(bad):  # a huge finite point is just far away: noise
        labels = OPS.dbscan(pts.to(d), 0.5, 3).cpu()
        assert torch.equal(labels, ref.dbscan(pts, 0.5, 3))
        assert labels[17] == -1
    else:
        with pytest.raises(RuntimeError, match="finite"):
            OPS.dbscan(pts.to(d), 0.5, 3)
        with pytest.raises(ValueError, match="finite"):
            ref.dbscan(pts, 0.5, 3)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("bad", BAD)
def test_problem_setup(device, dtype, bad):
    d = _dev(device)
    g = torch.Generator().manual_seed(14)
    pts = _points(70, dtype, bad, seed=15)
    labels = torch.randint(-1, 3, (70,), generator=g)
    args = (ORIGIN, SPACING, list(SHAPE), 32)
    if math.isfinite(bad):  # huge coordinates clamp into the lattice, exactly like the reference
        got = OPS.problem_setup(pts.to(d), labels.to(d), *args)
        want = ref.problem_setup(pts, labels, *args)
        for k, (x, y) in enumerate(zip(got, want)):
            if isinstance(x, int):
                assert x == y, k
            else:
                assert torch.equal(x.cpu(), y), k
    else:
        with pytest.raises(RuntimeError, match="finite"):
            OPS.problem_setup(pts.to(d), labels.to(d), *args)
        with pytest.raises(ValueError, match="finite"):
            ref.problem_setup(pts, labels, *args)


# --- host scalars ----------------------------------------------------------------------------

@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_nonfinite_scalars_raise(device, value):
    d = _dev(device)
    pts = torch.rand(5, 3, device=d)
    grid = torch.rand(1, *SHAPE, device=d)
    origin = [0.0, value, 0.0]
    cases = [
        ("origin", lambda: OPS.trilinear_gather(grid, pts, origin, SPACING)),
        ("origin", lambda: OPS.trilinear_scatter(pts[:, :1], pts, origin, SPACING, list(SHAPE))),
        ("origin", lambda: OPS.points_to_occupancy(pts, origin, SPACING, list(SHAPE))),
        ("origin", lambda: OPS.problem_setup(pts, None, origin, SPACING, list(SHAPE), 32)),
        ("spacing", lambda: OPS.trilinear_gather(grid, pts, ORIGIN, value)),
        ("spacing", lambda: OPS.trilinear_scatter(pts[:, :1], pts, ORIGIN, value, list(SHAPE))),
        ("spacing", lambda: OPS.points_to_occupancy(pts, ORIGIN, value, list(SHAPE))),
        ("spacing", lambda: OPS.edt(torch.ones(2, 2, 2, dtype=torch.bool, device=d), value)),
        ("spacing", lambda: OPS.problem_setup(pts, None, ORIGIN, value, list(SHAPE), 32)),
        ("spacing", lambda: OPS.dt_loss(pts, pts, [grid[0]], ORIGIN, value, [1.0], [1.0], 2.0)),
        ("origins", lambda: OPS.dt_loss(pts, pts, [grid[0]], origin, SPACING, [1.0], [1.0], 2.0)),
        ("time_offsets", lambda: OPS.dt_loss(pts, pts, [grid[0]], ORIGIN, SPACING, [value], [1.0], 2.0)),
        ("weights", lambda: OPS.dt_loss(pts, pts, [grid[0]], ORIGIN, SPACING, [1.0], [value], 2.0)),
        ("eps", lambda: OPS.dbscan(pts, value, 3)),
    ]
    if not value > 0:  # +inf truncation is allowed: no truncation
        cases.append(("truncation", lambda: OPS.dt_loss(pts, pts, [grid[0]], ORIGIN, SPACING, [1.0], [1.0], value)))
    for name, fn in cases:
        with pytest.raises(RuntimeError, match=name):
            fn()


def test_tiny_spacing_and_huge_grid_shape_raise():
    pts = torch.rand(5, 3)
    with pytest.raises(RuntimeError, match="spacing"):
        OPS.trilinear_gather(torch.rand(1, 2, 2, 2), pts, ORIGIN, 1e-40)
    for op in (lambda s: OPS.trilinear_scatter(pts[:, :1], pts, ORIGIN, SPACING, s),
               lambda s: OPS.points_to_occupancy(pts, ORIGIN, SPACING, s),
               lambda s: OPS.problem_setup(pts, None, ORIGIN, SPACING, s, 32)):
        with pytest.raises(RuntimeError, match="grid_shape"):
            op([2**31, 2**31, 2**31])
    # (N, C) values with a huge C and no rows: the output grid's size must not wrap around
    with pytest.raises(RuntimeError, match="too many elements"):
        OPS.trilinear_scatter(torch.zeros(0, 2**40), torch.zeros(0, 3), ORIGIN, SPACING, [2**10] * 3)
