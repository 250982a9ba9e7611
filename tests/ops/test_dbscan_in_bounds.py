"""dbscan_in_bounds (DBSCAN whose grid is sized from given bounds: on CUDA nothing is read
back): dbscan's labels wherever the bounds hold (exactly the points' bounds, or wider),
``outside`` 1 for a point outside them or not finite, bad bounds refused; the reference and
opcheck; on a GPU the CUDA kernel against dbscan's."""

import numpy as np
import pytest
import torch

from floxels_ext import ops
from floxels_ext.reference import ops as reference

F = torch.ops.floxels


def _cloud(n, seed, dtype=torch.float32):
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-6, 6, (8, 3))
    pts = centres[rng.integers(0, 8, n)] + rng.normal(0, 0.35, (n, 3))
    return torch.from_numpy(pts).to(dtype)


def _exact(p):
    return [*p.double().min(0).values.tolist(), *p.double().max(0).values.tolist()]


def _check(p, eps=0.5, ms=4):
    want = ops.dbscan(p, eps, ms)
    for b in (_exact(p), [v - 3.0 for v in _exact(p)[:3]] + [v + 7.5 for v in _exact(p)[3:]]):
        lab, out = ops.dbscan_in_bounds(p, eps, ms, b)
        assert out.dtype == torch.int32 and out.shape == (1,) and int(out) == 0
        assert torch.equal(lab, want)
        ref_lab, ref_out = reference.dbscan_in_bounds(p, eps, ms, b)
        if p.shape[0] <= 800:  # (the reference is O(N^2))
            assert torch.equal(ref_lab.cpu(), want.cpu()) and int(ref_out) == 0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("n", [1, 7, 500, 3000])
def test_labels_are_dbscans_wherever_the_bounds_hold(dtype, n):
    _check(_cloud(n, n, dtype))


@pytest.mark.parametrize("bad", ["below", "above", "nan", "inf"])
def test_a_point_outside_the_bounds_is_flagged(bad):
    p = _cloud(400, 3)
    b = _exact(p)
    q = p.clone()
    q[123] = {"below": torch.tensor([b[0] - 0.01, 0.0, 0.0]), "above": torch.tensor([0.0, 0.0, b[5] + 0.01]),
              "nan": torch.tensor([float("nan"), 0.0, 0.0]), "inf": torch.tensor([0.0, float("inf"), 0.0])}[bad]
    lab, out = ops.dbscan_in_bounds(q, 0.5, 4, b)
    assert int(out) == 1 and bool((lab == -1).all())
    ref_lab, ref_out = reference.dbscan_in_bounds(q, 0.5, 4, b)
    assert int(ref_out) == 1 and torch.equal(ref_lab, lab)


def test_bad_bounds_are_refused():
    p = _cloud(50, 1)
    b = _exact(p)
    for bounds, msg in (([0.0] * 5, "6 values"), (b[:3] + [float("nan"), 1.0, 1.0], "finite"),
                        ([1.0, 0.0, 0.0, 0.0, 1.0, 1.0], "min <= max")):
        with pytest.raises(RuntimeError, match=msg):
            F.dbscan_in_bounds(p, 0.5, 4, bounds)
    with pytest.raises(RuntimeError, match="eps"):
        F.dbscan_in_bounds(p, -1.0, 4, b)


def test_opcheck():
    p = _cloud(64, 2)
    torch.library.opcheck(F.dbscan_in_bounds, (p, 0.5, 3, _exact(p)))
    torch.library.opcheck(F.dbscan_in_bounds, (p.double(), 0.5, 3, _exact(p)))


@pytest.mark.cuda
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("n", [7, 3000, 60000])
def test_cuda_labels_are_dbscans(dtype, n):
    p = _cloud(n, n + 1, dtype).cuda()
    _check(p)
    _check(p, eps=0.3, ms=1)


@pytest.mark.cuda
@pytest.mark.parametrize("bad", ["below", "nan"])
def test_cuda_flags_points_outside(bad):
    p = _cloud(5000, 4)
    b = _exact(p)
    p[77] = torch.tensor([b[0] - 0.5, 0.0, 0.0]) if bad == "below" else torch.tensor([0.0, float("nan"), 0.0])
    _, out = ops.dbscan_in_bounds(p.cuda(), 0.5, 4, b)
    assert out.is_cuda and int(out) == 1
