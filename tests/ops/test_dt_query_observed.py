"""The optional ``observed`` bits of ``floxels::dt_residual`` and ``floxels::dt_evidence``
(``FloxelsConfig.range_mask`` / ``visibility``, estimator/sight.py): scan k's term counts for
point i only where bit k of ``observed[i]`` is set; against the pure-PyTorch reference and a
per-scan recomputation, CPU and CUDA."""

from __future__ import annotations

import pytest
import torch

import floxels_ext  # noqa: F401  (registers torch.ops.floxels.*)
from floxels_ext.ops import dt_evidence, dt_residual
from floxels_ext.reference import ops as ref
from test_dt_query import TOL, make_case, qargs, runs

ops = torch.ops.floxels
cuda = pytest.mark.cuda


def bits_for(c, seed=0, device="cpu"):
    """(N,) int32 random bits over the case's K scans (about 2 in 3 set), bit 31 used when K = 32."""
    g = torch.Generator().manual_seed(seed)
    n, K = c["points"].shape[0], len(c["dts"])
    on = torch.rand(n, K, generator=g) < 0.65
    bits = torch.zeros(n, dtype=torch.int64)
    for k in range(K):
        bits |= on[:, k].long() << k
    return bits.to(torch.int32).to(device), on


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("squared", [False, True])
def test_residual_with_bits_matches_reference_and_per_scan_sums(dtype, squared):
    c = make_case(4, 900, dtype, seed=5)
    b, on = bits_for(c)
    got = dt_residual(*qargs(c), c["weights"], c["cap"], squared, observed=b)
    torch.testing.assert_close(got, ref.dt_residual(*qargs(c), c["weights"], c["cap"], squared, b), **TOL[dtype])
    assert torch.equal(ops.dt_residual(*qargs(c), c["weights"], c["cap"], squared, b), got)
    want = torch.zeros_like(got)
    p, m, dts, o, sp, t = qargs(c)
    for k in range(4):
        one = dt_residual(p, m, [dts[k]], o[3 * k:3 * k + 3], sp, [t[k]], [c["weights"][k]], c["cap"], squared)
        want += torch.where(on[:, k], one, torch.zeros_like(one))
    torch.testing.assert_close(got, want, **TOL[dtype])


def test_all_bits_change_nothing_and_bit_31_counts():
    c = make_case(3, 500, torch.float64, seed=2)
    every = torch.full((500,), -1, dtype=torch.int32)  # all 32 bits
    a = dt_residual(*qargs(c), c["weights"], c["cap"], False)
    assert torch.equal(dt_residual(*qargs(c), c["weights"], c["cap"], False, observed=every), a)
    cells = torch.arange(500) // 10
    args = (c["points"], c["motion"], None, cells, c["dts"], c["origins"], c["spacing"], c["time_offsets"],
            c["weights"], c["cap"], 0.02, 0.05)
    for x, y in zip(dt_evidence(*args), dt_evidence(*args, observed=every)):
        assert torch.equal(x, y)
    none = torch.zeros(500, dtype=torch.int32)
    assert torch.equal(dt_residual(*qargs(c), c["weights"], c["cap"], False, observed=none), torch.zeros(500,
                                                                                                      dtype=torch.float64))
    c32 = make_case(32, 200, torch.float64, seed=6)
    b, on = bits_for(c32, seed=4)
    assert on[:, 31].any() and (b < 0).any()
    torch.testing.assert_close(dt_residual(*qargs(c32), c32["weights"], c32["cap"], False, observed=b),
                               ref.dt_residual(*qargs(c32), c32["weights"], c32["cap"], False, b))


def evidence_case(K, n, dtype, seed, bits_seed, runs_seed):
    """A random case with its bits and group keys (labelled runs, cells)."""
    c = make_case(K, n, dtype, seed=seed)
    return (c, bits_for(c, seed=bits_seed)[0], *runs(n, runs_seed))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_evidence_with_bits_matches_reference(dtype):
    n = 2500
    c, b, lab, cells = evidence_case(4, n, dtype, 21, 1, 2)
    a = (c["points"], c["motion"], lab, cells, c["dts"], c["origins"], c["spacing"], c["time_offsets"],
         c["weights"], c["cap"], 0.02, 0.05)
    got, want = dt_evidence(*a, observed=b), ref.dt_evidence(*a, observed=b)
    for k in (0, 2, 3):
        torch.testing.assert_close(got[k], want[k], **TOL[dtype])
    clear = (want[0] - torch.clamp(want[3] * 0.05, min=0.02)).abs() > 1e-4
    assert torch.equal(got[1][clear], want[1][clear])
    assert not torch.equal(dt_evidence(*a)[3], got[3])  # the bits changed the residuals


def test_observed_bad_input():
    c = make_case(2, 50, torch.float64)
    args = (*qargs(c), c["weights"], c["cap"], False)
    with pytest.raises(ValueError, match=r"observed must be an \(50,\) int32 tensor"):
        dt_residual(*args, observed=torch.zeros(49, dtype=torch.int32))
    with pytest.raises(ValueError, match="int32"):
        dt_residual(*args, observed=torch.zeros(50, dtype=torch.int64))
    with pytest.raises(TypeError):
        dt_residual(*args, observed=[0] * 50)
    with pytest.raises(RuntimeError, match=r"observed must have shape"):  # the raw op checks too
        ops.dt_residual(*args, torch.zeros(3, dtype=torch.int32))
    with pytest.raises(RuntimeError, match="observed must be int32"):
        ops.dt_residual(*args, torch.zeros(50, dtype=torch.float32))


def test_opcheck_with_bits():
    c = make_case(2, 40, torch.float64)
    b, _ = bits_for(c)
    cells = torch.arange(40) // 4
    torch.library.opcheck(ops.dt_residual, (*qargs(c), c["weights"], 1.0, True, b))
    torch.library.opcheck(ops.dt_evidence, (c["points"], c["motion"], None, cells, c["dts"], c["origins"],
                                            c["spacing"], c["time_offsets"], c["weights"], 1.0, 0.02, 0.05, b))


@cuda
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cuda_bits_match_cpu_and_repeat_bytes(dtype):
    c, b, lab, cells = evidence_case(5, 30000, dtype, 33, 3, 4)
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
