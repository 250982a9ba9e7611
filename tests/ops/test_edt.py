"""Exact EDT and point-cloud occupancy: ours vs scipy and the pure-PyTorch reference."""

import numpy as np
import pytest
import torch
from scipy import ndimage

import floxels_ext.ops as F
from floxels_ext.reference import ops as R

ops = torch.ops.floxels
cuda = pytest.mark.cuda
needs_gpu = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


def random_occupancy(shape, k, gen):
    occ = torch.zeros(int(np.prod(shape)), dtype=torch.bool)
    if k:
        occ[torch.randint(0, occ.numel(), (k,), generator=gen)] = True
    return occ.view(shape)


def scipy_edt(occ: torch.Tensor, spacing: float = 1.0) -> torch.Tensor:
    out = ndimage.distance_transform_edt(~occ.cpu().numpy(), sampling=spacing)
    return torch.from_numpy(out.astype(np.float32))


def ulp_diff(a: torch.Tensor, b: torch.Tensor) -> int:
    """Largest distance in float32 units in the last place (both finite, non-negative)."""
    assert torch.isfinite(a).all() and torch.isfinite(b).all()
    return int((a.view(torch.int32).long() - b.view(torch.int32).long()).abs().max()) if a.numel() else 0


SHAPES = [(1, 40, 50), (7, 33, 45), (12, 64, 48), (3, 1, 80), (20, 20, 1), (9, 2, 2), (16, 70, 90)]


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("density", [0.0005, 0.01, 0.3])
def test_edt_exact_vs_scipy(shape, density):
    gen = torch.Generator().manual_seed(hash((shape, density)) % 2**31)
    n = int(np.prod(shape))
    occ = random_occupancy(shape, max(1, int(n * density)), gen)
    assert torch.equal(F.edt(occ, 1.0), scipy_edt(occ))
    # Non-unit spacing: scipy scales each axis before summing, we scale the root: <= 1 ulp.
    assert ulp_diff(F.edt(occ, 0.1), scipy_edt(occ, 0.1)) <= 1


def test_edt_anisotropic():
    gen = torch.Generator().manual_seed(1)
    occ = random_occupancy((8, 300, 250), 400, gen)
    occ[:, 0, :] = False  # leave empty rows/columns to exercise the skipping paths
    assert torch.equal(F.edt(occ, 1.0), scipy_edt(occ))
    assert ulp_diff(F.edt(occ, 0.2), scipy_edt(occ, 0.2)) <= 1


def test_edt_long_z_uses_envelope_path():
    # Z above the CPU search-variant threshold.
    gen = torch.Generator().manual_seed(2)
    occ = random_occupancy((300, 6, 5), 12, gen)
    assert torch.equal(F.edt(occ, 1.0), scipy_edt(occ))


@pytest.mark.parametrize("shape", [(1, 1, 1), (1, 17, 23), (5, 1, 9), (6, 7, 1), (11, 13, 17)])
def test_edt_single_points_and_corners(shape):
    Z, Y, X = shape
    spots = [(0, 0, 0), (Z - 1, Y - 1, X - 1), (Z // 2, Y // 2, X // 2), (0, Y - 1, X // 2), (Z - 1, 0, 0)]
    for spot in spots:
        occ = torch.zeros(shape, dtype=torch.bool)
        occ[spot] = True
        assert torch.equal(F.edt(occ), scipy_edt(occ)), spot
    occ = torch.zeros(shape, dtype=torch.bool)
    for spot in spots:
        occ[spot] = True
    assert torch.equal(F.edt(occ), scipy_edt(occ))


def test_edt_all_occupied_and_empty():
    assert torch.equal(F.edt(torch.ones(4, 5, 6, dtype=torch.bool)), torch.zeros(4, 5, 6))
    empty = F.edt(torch.zeros(4, 5, 6, dtype=torch.bool), 0.5)
    assert empty.dtype == torch.float32 and torch.isinf(empty).all() and (empty > 0).all()
    assert F.edt(torch.zeros(0, 5, 6, dtype=torch.bool)).shape == (0, 5, 6)


@pytest.mark.parametrize("seed", range(4))
def test_edt_vs_reference(seed):
    gen = torch.Generator().manual_seed(seed)
    shape = tuple(int(v) for v in torch.randint(1, 9, (3,), generator=gen))
    occ = random_occupancy(shape, int(torch.randint(0, 4, (1,), generator=gen)), gen)
    assert torch.equal(F.edt(occ, 0.25), R.edt(occ, 0.25))


def test_edt_noncontiguous_input():
    gen = torch.Generator().manual_seed(3)
    occ = random_occupancy((20, 30, 10), 15, gen).transpose(0, 2)
    assert torch.equal(F.edt(occ), scipy_edt(occ))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_points_to_occupancy_vs_reference(dtype):
    gen = torch.Generator().manual_seed(4)
    origin, spacing, shape = [-1.0, 2.0, -0.5], 0.25, [6, 9, 11]
    for n in (0, 1, 500):
        pts = (torch.rand(n, 3, generator=gen, dtype=torch.float64) * 5 - 2).to(dtype)
        ours = F.points_to_occupancy(pts, origin, spacing, shape)
        assert ours.dtype == torch.bool and ours.shape == tuple(shape)
        assert torch.equal(ours, R.points_to_occupancy(pts, origin, spacing, shape))


def test_points_to_occupancy_half_positions_and_outside():
    origin, spacing = [0.0, 0.0, 0.0], 0.5
    # exactly half-way between samples rounds up; -0.25 rounds to 0 (inside), -0.3 is outside
    pts = torch.tensor([[0.25, 0.75, 0.0], [-0.25, 0.0, 0.0], [-0.3, 0.0, 0.0], [1.24, 1.0, 1.2],
                        [100.0, 0.0, 0.0], [0.0, 0.0, -7.0]])
    occ = F.points_to_occupancy(pts, origin, spacing, [3, 3, 3])
    expected = torch.zeros(3, 3, 3, dtype=torch.bool)
    expected[0, 2, 1] = True
    expected[0, 0, 0] = True
    expected[2, 2, 2] = True
    assert torch.equal(occ, expected)
    assert torch.equal(occ, R.points_to_occupancy(pts, origin, spacing, [3, 3, 3]))


def test_distance_transform_and_grid_cap():
    gen = torch.Generator().manual_seed(5)
    pts = torch.rand(300, 3, generator=gen) * torch.tensor([4.0, 3.0, 1.0])
    dt, origin = F.distance_transform(pts, spacing=0.1, padding=0.3)
    o, shape = F.grid_for_points(pts, 0.1, 0.3)
    assert origin == o and list(dt.shape) == shape
    occ = R.points_to_occupancy(pts, o, 0.1, shape)
    assert torch.equal(dt, ops.edt(occ, 0.1))
    assert ulp_diff(dt, scipy_edt(occ, 0.1)) <= 1
    far = torch.tensor([[0.0, 0.0, 0.0], [1e5, 1e5, 10.0]])
    with pytest.raises(F.GridTooLargeError, match="samples"):
        F.distance_transform(far, spacing=0.1)


def test_bad_inputs():
    occ = torch.zeros(3, 4, 5, dtype=torch.bool)
    with pytest.raises(TypeError, match="bool"):
        F.edt(occ.float())
    with pytest.raises(ValueError, match="Z, Y, X"):
        F.edt(occ[0])
    with pytest.raises(RuntimeError, match="bool"):
        ops.edt(occ.to(torch.uint8), 1.0)
    with pytest.raises(RuntimeError, match="Z, Y, X"):
        ops.edt(occ[0], 1.0)
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="spacing"):
            F.edt(occ, bad)
        with pytest.raises(RuntimeError, match="spacing"):
            ops.edt(occ, bad)
    pts = torch.zeros(4, 3)
    pts[2, 1] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        F.points_to_occupancy(pts, [0, 0, 0], 0.1, [2, 2, 2])
    with pytest.raises(ValueError, match="spacing"):
        F.points_to_occupancy(torch.zeros(4, 3), [0, 0, 0], 0.0, [2, 2, 2])
    with pytest.raises(RuntimeError, match="spacing"):
        ops.points_to_occupancy(torch.zeros(4, 3), [0.0, 0.0, 0.0], -1.0, [2, 2, 2])
    with pytest.raises(ValueError, match="grid_shape"):
        F.points_to_occupancy(torch.zeros(4, 3), [0, 0, 0], 0.1, [2, 2])
    with pytest.raises(RuntimeError, match="grid_shape"):
        ops.points_to_occupancy(torch.zeros(4, 3), [0.0, 0.0, 0.0], 0.1, [2, 0, 2])
    with pytest.raises(TypeError, match="float32 or float64"):
        F.points_to_occupancy(torch.zeros(4, 3, dtype=torch.int32), [0, 0, 0], 0.1, [2, 2, 2])
    with pytest.raises(RuntimeError, match=r"\(N, 3\)"):
        ops.points_to_occupancy(torch.zeros(4, 2), [0.0, 0.0, 0.0], 0.1, [2, 2, 2])
    with pytest.raises(RuntimeError, match="origin"):
        ops.points_to_occupancy(torch.zeros(4, 3), [0.0, 0.0], 0.1, [2, 2, 2])
    with pytest.raises(RuntimeError, match="too large"):
        ops.edt(torch.zeros(2, 1, 60000, dtype=torch.bool), 1.0)  # 59999^2 overflows int32


def test_opcheck():
    gen = torch.Generator().manual_seed(6)
    occ = random_occupancy((4, 5, 6), 3, gen)
    torch.library.opcheck(ops.edt.default, (occ, 0.5))
    pts = torch.rand(20, 3, generator=gen)
    torch.library.opcheck(ops.points_to_occupancy.default, (pts, [0.0, 0.0, 0.0], 0.2, [4, 5, 6]))


@cuda
@needs_gpu
@pytest.mark.parametrize("shape,k", [((7, 33, 45), 30), ((1, 40, 50), 3), ((30, 130, 70), 600),
                                     ((300, 6, 5), 10), ((5, 5, 5), 0), ((3, 4, 5), 60)])
def test_cuda_matches_cpu(shape, k):
    gen = torch.Generator().manual_seed(7)
    occ = random_occupancy(shape, k, gen)
    for spacing in (1.0, 0.1):
        assert torch.equal(F.edt(occ.cuda(), spacing).cpu(), F.edt(occ, spacing))


@cuda
@needs_gpu
def test_cuda_anisotropic_vs_scipy():
    gen = torch.Generator().manual_seed(8)
    occ = random_occupancy((12, 400, 300), 2000, gen)
    assert torch.equal(F.edt(occ.cuda()).cpu(), scipy_edt(occ))


@cuda
@needs_gpu
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cuda_points_to_occupancy(dtype):
    gen = torch.Generator().manual_seed(9)
    pts = (torch.rand(1000, 3, generator=gen, dtype=torch.float64) * 6 - 2).to(dtype)
    pts[:4] = torch.tensor([[0.25, 0.75, 0.0], [-0.25, 0.0, 0.0], [-0.3, 0.0, 0.0], [1.25, 1.0, 1.25]], dtype=dtype)
    args = ([0.0, 0.0, 0.0], 0.5, [5, 6, 7])
    assert torch.equal(F.points_to_occupancy(pts.cuda(), *args).cpu(), F.points_to_occupancy(pts, *args))
    torch.library.opcheck(ops.points_to_occupancy.default, (pts.cuda(), *args))
    torch.library.opcheck(ops.edt.default, (F.points_to_occupancy(pts.cuda(), *args), 0.5))
