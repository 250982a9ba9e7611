"""floxels::dt_residual / dt_sample / dt_evidence (data-only DT look-ups of the dt_loss family)
against reference.* on fresh random inputs; non-finite rows; bad input; opcheck; CUDA."""

from __future__ import annotations

import math

import pytest
import torch

import floxels_ext  # noqa: F401  (registers torch.ops.floxels.*)
from floxels_ext.ops import dt_evidence, dt_residual, dt_sample
from floxels_ext.reference import ops as ref
from test_dt_loss import make_case as dt_loss_case

ops = torch.ops.floxels
cuda = pytest.mark.cuda


def make_case(K, n, dtype=torch.float64, seed=0, device="cpu"):
    """test_dt_loss's random case (K DTs of different shapes/origins, exact EDTs and random
    fields; n points partly outside every grid), its flow as the motion and its truncation,
    inside the value range, as the cap."""
    c = dt_loss_case(K, n, dtype, seed, device)
    c["motion"], c["cap"] = c.pop("flow"), c.pop("truncation")
    return c


def qargs(c):
    return c["points"], c["motion"], c["dts"], c["origins"], c["spacing"], c["time_offsets"]


def runs(n, seed, device="cpu", with_labels=True):
    """Group keys as the solver orders them: labelled runs (some long), unlabelled runs of cells
    (a cell may come back later: a new run)."""
    g = torch.Generator().manual_seed(seed)
    lengths = torch.randint(1, 40, (n,), generator=g)
    lengths[::7] = torch.randint(100, 700, (lengths[::7].numel(),), generator=g)
    rid = torch.repeat_interleave(torch.arange(n), lengths)[:n]
    lab = torch.where(rid % 3 == 0, torch.full_like(rid, -1), rid // 2)
    cells = (rid % 5).to(torch.int32)
    return (lab.to(device) if with_labels else None), cells.to(device)


TOL = {torch.float64: dict(rtol=1e-10, atol=1e-10), torch.float32: dict(rtol=2e-4, atol=2e-4)}


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("K", [1, 3, 6])
@pytest.mark.parametrize("squared", [False, True])
def test_residual_matches_reference(dtype, K, squared):
    c = make_case(K, 700, dtype, seed=K)
    got = dt_residual(*qargs(c), c["weights"], c["cap"], squared)
    want = ref.dt_residual(*qargs(c), c["weights"], c["cap"], squared)
    assert got.dtype == dtype and got.shape == (700,)
    torch.testing.assert_close(got, want, **TOL[dtype])
    raw = ops.dt_residual(*qargs(c), c["weights"], c["cap"], squared)
    assert torch.equal(raw, got)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("K", [1, 4])
def test_sample_matches_reference_and_gather_backward(dtype, K):
    c = make_case(K, 600, dtype, seed=10 + K)
    got = dt_sample(*qargs(c))
    want = ref.dt_sample(*qargs(c))
    assert got.shape == (K, 600, 4) and got.dtype == dtype
    tol = TOL[dtype] if dtype == torch.float64 else dict(rtol=2e-3, atol=2e-3)
    torch.testing.assert_close(got, want, **tol)
    if dtype == torch.float64:  # the gradient trilinear_gather's backward gives
        for k in range(K):
            q = (c["points"] + c["time_offsets"][k] * c["motion"]).requires_grad_(True)
            v = ops.trilinear_gather(c["dts"][k][None].double(), q, c["origins"][3 * k:3 * k + 3], c["spacing"])
            (gq,) = torch.autograd.grad(v.sum(), q)
            torch.testing.assert_close(got[k, :, 1:], gq, rtol=1e-9, atol=1e-9)
            torch.testing.assert_close(got[k, :, 0], v[:, 0].detach(), rtol=1e-12, atol=1e-12)


def test_residual_is_sample_combined():
    c = make_case(5, 400, torch.float64, seed=3)
    s = dt_sample(*qargs(c))[:, :, 0].clamp_max(c["cap"])
    w = torch.tensor(c["weights"], dtype=torch.float64)[:, None]
    torch.testing.assert_close(dt_residual(*qargs(c), c["weights"], c["cap"], True), (w * s * s).sum(0))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("with_labels", [True, False])
def test_evidence_matches_reference(dtype, with_labels):
    n = 3000
    c = make_case(4, n, dtype, seed=20)
    lab, cells = runs(n, 1, with_labels=with_labels)
    a = (c["points"], c["motion"], lab, cells, c["dts"], c["origins"], c["spacing"], c["time_offsets"],
         c["weights"], c["cap"], 0.02, 0.05)
    got = dt_evidence(*a)
    want = ref.dt_evidence(*a)
    for g, w in zip(got, want):
        assert g.shape == (n,) and g.dtype == w.dtype
    assert got[0].dtype == dtype and got[1].dtype == torch.bool
    for k in (0, 2, 3):
        torch.testing.assert_close(got[k], want[k], **TOL[dtype])
    # the test itself, where it is not a tie at float rounding
    clear = (want[0] - torch.clamp(want[3] * 0.05, min=0.02)).abs() > 1e-4
    assert clear.float().mean() > 0.9 and torch.equal(got[1][clear], want[1][clear])
    # one value per group: runs of equal keys
    same = cells[1:] == cells[:-1]
    if lab is not None:
        same = (lab[1:] == lab[:-1]) & ((lab[1:] >= 0) | same)
    assert torch.equal(got[3][1:][same], got[3][:-1][same])


def test_evidence_int64_strided_cells_and_thread_counts():
    n = 2500
    c = make_case(3, n, torch.float32, seed=5)
    lab, cells = runs(n, 2)
    wide = torch.stack([cells.long()] * 8, 1)  # like corner_idx[:, 0]: stride 8
    a = (c["dts"], c["origins"], c["spacing"], c["time_offsets"], c["weights"], c["cap"], 0.02, 0.05)
    base = ops.dt_evidence(c["points"], c["motion"], lab, cells, *a)
    strided = ops.dt_evidence(c["points"], c["motion"], lab.to(torch.int32), wide[:, 0], *a)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = ops.dt_evidence(c["points"], c["motion"], lab, cells, *a)
    finally:
        torch.set_num_threads(threads)
    for x, y, z in zip(base, strided, one):
        assert torch.equal(x, y) and torch.equal(x, z)


def test_non_finite_rows():
    c = make_case(3, 300, torch.float64, seed=7)
    c["points"][5, 1] = math.nan
    c["motion"][9, 0] = math.inf
    r = ops.dt_residual(*qargs(c), c["weights"], c["cap"], False)
    assert torch.isnan(r[[5, 9]]).all() and torch.isfinite(r[torch.arange(300) % 300 > 9]).all()
    s = ops.dt_sample(*qargs(c))
    assert torch.isnan(s[:, [5, 9], 0]).all() and (s[:, [5, 9], 1:] == 0).all()
    torch.testing.assert_close(r, ref.dt_residual(*qargs(c), c["weights"], c["cap"], False), equal_nan=True)
    torch.testing.assert_close(s, ref.dt_sample(*qargs(c)), equal_nan=True)
    # evidence: only the groups of the bad rows are NaN / unexplained
    cells = torch.arange(300, dtype=torch.int64) // 10
    sc, ex, rf, rz = ops.dt_evidence(c["points"], c["motion"], None, cells, c["dts"], c["origins"], c["spacing"],
                                     c["time_offsets"], c["weights"], c["cap"], 0.02, 0.05)
    bad = cells == 0
    assert torch.isnan(sc[bad]).all() and not ex[bad].any() and torch.isnan(rf[bad]).all()
    assert torch.isfinite(sc[~bad]).all() and torch.isfinite(rz[~bad]).all()


def test_empty_points():
    c = make_case(2, 0, torch.float32)
    assert ops.dt_residual(*qargs(c), c["weights"], 1.0, False).shape == (0,)
    assert ops.dt_sample(*qargs(c)).shape == (2, 0, 4)
    out = ops.dt_evidence(c["points"], c["motion"], None, torch.zeros(0, dtype=torch.long), c["dts"], c["origins"],
                          c["spacing"], c["time_offsets"], c["weights"], 1.0, 0.02, 0.05)
    assert [t.shape for t in out] == [(0,)] * 4


def test_bad_input():
    c = make_case(2, 50, torch.float32)
    p, m, dts, o, sp, t = qargs(c)
    w, cap = c["weights"], c["cap"]
    cells = torch.zeros(50, dtype=torch.long)
    # raw ops (C++ checks): RuntimeError naming the problem
    with pytest.raises(RuntimeError, match="float32 or float64"):
        ops.dt_residual(p.long(), m.long(), dts, o, sp, t, w, cap, False)
    with pytest.raises(RuntimeError, match="motion must have the shape"):
        ops.dt_residual(p, m[:10], dts, o, sp, t, w, cap, False)
    with pytest.raises(RuntimeError, match="points is Float but motion is Double"):
        ops.dt_sample(p, m.double(), dts, o, sp, t)
    with pytest.raises(RuntimeError, match="at least one distance transform"):
        ops.dt_sample(p, m, [], [], sp, [])
    with pytest.raises(RuntimeError, match="at most 32"):
        ops.dt_residual(p, m, [dts[0]] * 33, o[:3] * 33, sp, [1.0] * 33, [1.0] * 33, cap, False)
    for bad_cap in (math.inf, math.nan, 0.0, -1.0):
        with pytest.raises(RuntimeError, match="cap must be positive and finite"):
            ops.dt_residual(p, m, dts, o, sp, t, w, bad_cap, False)
        with pytest.raises(ValueError, match="cap must be positive and finite"):
            dt_residual(p, m, dts, o, sp, t, w, bad_cap)
    with pytest.raises(RuntimeError, match="dts\\[1\\] must be float32"):
        ops.dt_sample(p, m, [dts[0], dts[1].double()], o, sp, t)
    with pytest.raises(RuntimeError, match="weights needs 2"):
        ops.dt_residual(p, m, dts, o, sp, t, w[:1], cap, False)
    with pytest.raises(RuntimeError, match="origins needs 3 values"):
        ops.dt_sample(p, m, dts, o[:5], sp, t)
    with pytest.raises(RuntimeError, match="cells must have shape"):
        ops.dt_evidence(p, m, None, cells[:3], dts, o, sp, t, w, cap, 0.02, 0.05)
    with pytest.raises(RuntimeError, match="cells must be int32 or int64"):
        ops.dt_evidence(p, m, None, cells.float(), dts, o, sp, t, w, cap, 0.02, 0.05)
    with pytest.raises(RuntimeError, match="margin must be finite"):
        ops.dt_evidence(p, m, None, cells, dts, o, sp, t, w, cap, math.nan, 0.05)
    # wrappers: ValueError / TypeError
    with pytest.raises(ValueError, match="at least one distance transform"):
        dt_sample(p, m, [], [], sp, [])
    with pytest.raises(ValueError, match="at most 32"):
        dt_sample(p, m, [dts[0]] * 33, o[:3] * 33, sp, [1.0] * 33)
    with pytest.raises(TypeError, match="motion is torch.float64"):
        dt_residual(p, m.double(), dts, o, sp, t, w, cap)
    with pytest.raises(ValueError, match="NaN or inf"):
        dt_sample(torch.full_like(p, math.nan), m, dts, o, sp, t)
    with pytest.raises(ValueError, match="labels must be"):
        dt_evidence(p, m, cells[:4], cells, dts, o, sp, t, w, cap, 0.02, 0.05)


def test_no_gradient_flows():
    c = make_case(2, 20, torch.float64)
    m = c["motion"].clone().requires_grad_(True)
    r = ops.dt_residual(c["points"], m, c["dts"], c["origins"], c["spacing"], c["time_offsets"], c["weights"], 1.0,
                        False)
    with pytest.raises(RuntimeError, match="data-only op"):
        r.sum().backward()
    s = ops.dt_sample(c["points"], m, c["dts"], c["origins"], c["spacing"], c["time_offsets"])
    with pytest.raises(RuntimeError, match="data-only op"):
        s.sum().backward()


def test_opcheck():
    c = make_case(2, 40, torch.float64)
    cells = torch.arange(40) // 4
    torch.library.opcheck(ops.dt_residual, (*qargs(c), c["weights"], 1.0, True))
    torch.library.opcheck(ops.dt_sample, qargs(c))
    torch.library.opcheck(ops.dt_evidence, (c["points"], c["motion"], None, cells, c["dts"], c["origins"],
                                            c["spacing"], c["time_offsets"], c["weights"], 1.0, 0.02, 0.05))


@cuda
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cuda_matches_cpu_reference_and_repeats_bytes(dtype):
    n = 40000  # many blocks; runs of up to 700 points cross block borders
    c = make_case(5, n, dtype, seed=31)
    lab, cells = runs(n, 3)
    d = {k: (v.cuda() if isinstance(v, torch.Tensor) else [x.cuda() for x in v] if k == "dts" else v)
         for k, v in c.items()}
    tol = TOL[dtype] if dtype == torch.float64 else dict(rtol=1e-5, atol=1e-5)
    for sq in (False, True):
        g1 = ops.dt_residual(*qargs(d), d["weights"], d["cap"], sq)
        g2 = ops.dt_residual(*qargs(d), d["weights"], d["cap"], sq)
        assert torch.equal(g1, g2)
        torch.testing.assert_close(g1.cpu(), ops.dt_residual(*qargs(c), c["weights"], c["cap"], sq), **tol)
    s1, s2 = ops.dt_sample(*qargs(d)), ops.dt_sample(*qargs(d))
    assert torch.equal(s1, s2)
    torch.testing.assert_close(s1.cpu(), ops.dt_sample(*qargs(c)),
                               **(tol if dtype == torch.float64 else dict(rtol=1e-4, atol=1e-4)))
    tail = (d["dts"], d["origins"], d["spacing"], d["time_offsets"], d["weights"], d["cap"], 0.02, 0.05)
    for L, C in ((lab, cells), (None, cells), (lab.int(), torch.stack([cells] * 8, 1)[:, 0])):
        e1 = ops.dt_evidence(d["points"], d["motion"], None if L is None else L.cuda(), C.cuda(), *tail)
        e2 = ops.dt_evidence(d["points"], d["motion"], None if L is None else L.cuda(), C.cuda(), *tail)
        for a, b in zip(e1, e2):
            assert torch.equal(a, b)  # same bytes on every run
        ec = ops.dt_evidence(c["points"], c["motion"], L, C, c["dts"], c["origins"], c["spacing"], c["time_offsets"],
                             c["weights"], c["cap"], 0.02, 0.05)
        for k in (0, 2, 3):
            torch.testing.assert_close(e1[k].cpu(), ec[k], **tol)
        clear = (ec[0] - torch.clamp(ec[3] * 0.05, min=0.02)).abs() > 1e-4
        assert torch.equal(e1[1].cpu()[clear], ec[1][clear])


@cuda
def test_cuda_evidence_non_finite_row_spoils_only_its_group():
    c = make_case(3, 5000, torch.float32, seed=8, device="cuda")
    c["points"][1000, 2] = math.nan
    cells = (torch.arange(5000, device="cuda") // 300)
    sc, ex, _, _ = ops.dt_evidence(c["points"], c["motion"], None, cells, c["dts"], c["origins"], c["spacing"],
                                   c["time_offsets"], c["weights"], c["cap"], 0.02, 0.05)
    bad = cells == 1000 // 300
    assert torch.isnan(sc[bad]).all() and not ex[bad].any() and torch.isfinite(sc[~bad]).all()


@cuda
def test_cuda_bad_device():
    c = make_case(2, 10, torch.float32)
    with pytest.raises((RuntimeError, ValueError), match="cpu|cuda"):
        ops.dt_residual(c["points"].cuda(), c["motion"], c["dts"], c["origins"], c["spacing"], c["time_offsets"],
                        c["weights"], 1.0, False)
    with pytest.raises(ValueError, match="one device"):
        dt_sample(c["points"].cuda(), c["motion"].cuda(), c["dts"], c["origins"], c["spacing"], c["time_offsets"])
