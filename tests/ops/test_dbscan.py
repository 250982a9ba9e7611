"""Exact DBSCAN: labels identical to scikit-learn (numbering, border points, ties at eps)."""

import numpy as np
import pytest
import torch

from floxels_ext import ops
from floxels_ext.reference import ops as reference

F = torch.ops.floxels


def sklearn_labels(points: torch.Tensor, eps: float, min_samples: int) -> np.ndarray:
    sklearn_cluster = pytest.importorskip("sklearn.cluster")  # lazily: the CUDA test needs no sklearn
    return sklearn_cluster.DBSCAN(eps=eps, min_samples=min_samples).fit(points.numpy()).labels_


def assert_same(points, eps, min_samples, check_reference=True):
    want = sklearn_labels(points, eps, min_samples)
    got = ops.dbscan(points, eps, min_samples)
    assert got.dtype == torch.int64 and got.shape == (points.shape[0],)
    np.testing.assert_array_equal(got.numpy(), want)
    if check_reference:
        np.testing.assert_array_equal(reference.dbscan(points, eps, min_samples).numpy(), want)


def blobs(n, k, spread, dtype, rng):
    centres = rng.uniform(-5, 5, (k, 3))
    pts = centres[rng.integers(0, k, n)] + rng.normal(0, spread, (n, 3))
    return torch.from_numpy(pts).to(dtype)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("seed", range(6))
def test_random_uniform(dtype, seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(12, 600))
    pts = torch.from_numpy(rng.uniform(0, 2, (n, 3))).to(dtype)
    for min_samples in (1, 2, 4, 10):
        assert_same(pts, float(rng.uniform(0.05, 0.4)), min_samples)


@pytest.mark.parametrize("seed", range(5))
def test_blobs(seed):
    rng = np.random.default_rng(100 + seed)
    pts = blobs(int(rng.integers(200, 1500)), 6, 0.3, torch.float32, rng)
    for eps, min_samples in ((0.2, 5), (0.35, 3), (0.5, 10), (0.15, 1)):
        assert_same(pts, eps, min_samples, check_reference=pts.shape[0] <= 800)


def test_lidar_like():
    from floxels_ext.evaluation.sim import simulate_sequence

    frame = simulate_sequence("crossing", num_frames=1, seed=0, small=True).frames[0]
    pts = torch.as_tensor(frame.points)[~torch.as_tensor(frame.ground)].float()
    assert pts.shape[0] > 1000
    for eps, min_samples in ((0.5, 4), (0.3, 8), (1.0, 2)):
        assert_same(pts, eps, min_samples, check_reference=False)


def test_border_point_between_two_clusters():
    # Two dense clusters, and a border point exactly eps from one core of each (core
    # index of the second cluster is smaller, so sklearn labels it first: cluster 0).
    a = [[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.2, 0.0, 0.0], [0.0, 0.1, 0.0]]
    b = [[2.0, 0.0, 0.0], [2.1, 0.0, 0.0], [2.0, 0.1, 0.0], [2.0, 0.0, 0.1]]
    mid = [[1.0, 0.0, 0.0], [1.1, 0.0, 0.0]]
    filler = [[10.0 + i, 10.0, 10.0] for i in range(8)]  # noise; keeps N >= 12 (sklearn's KD-tree)
    for order in (a + b + mid + filler, b + a + mid + filler, mid + filler + a + b, mid + b + filler + a):
        pts = torch.tensor(order, dtype=torch.float64)
        for eps in (0.8, 0.9, 0.95):
            assert_same(pts, eps, 4)


def test_duplicates():
    rng = np.random.default_rng(7)
    base = rng.uniform(0, 1, (40, 3))
    pts = torch.from_numpy(np.concatenate([base, base, base[:10], base[:3]]))
    for min_samples in (1, 2, 3, 4, 5):
        assert_same(pts, 0.1, min_samples)
    same = torch.ones(30, 3)  # all coincident: one cell, one cluster
    assert_same(same, 0.01, 30)
    assert_same(same, 0.01, 31)


def test_exact_eps_ties():
    # Lattice with spacing equal to eps (exactly representable): neighbours at exactly eps
    # count (<=), diagonals do not.
    g = torch.stack(torch.meshgrid(*(torch.arange(5.0),) * 3, indexing="ij"), -1).reshape(-1, 3) * 0.5
    for min_samples in (2, 5, 6, 7, 8):
        assert_same(g, 0.5, min_samples)
    # float32 coordinates whose float64 distance is within one ulp of a decimal eps.
    rng = np.random.default_rng(3)
    for eps in (0.1, 0.3, 0.7):
        x = rng.uniform(0, 3, 60).astype(np.float32)
        pts = np.zeros((120, 3), np.float32)
        pts[:60, 0] = x
        pts[60:, 0] = x + np.float32(eps)
        pts[:, 1] = rng.integers(0, 3, 120) * 5
        for min_samples in (1, 2, 3):
            assert_same(torch.from_numpy(pts), eps, min_samples)


def test_min_samples_above_n_and_large_eps():
    rng = np.random.default_rng(9)
    pts = torch.from_numpy(rng.uniform(0, 1, (50, 3)))
    assert_same(pts, 0.2, 51)
    assert_same(pts, 0.2, 1000)
    assert_same(pts, 100.0, 3)


def test_degenerate_extent():
    # Huge extent relative to eps: the grid is never allocated over the bounding box.
    pts = torch.tensor([[0.0, 0.0, 0.0], [1e-9, 0.0, 0.0], [1e7, -1e7, 1e7], [1e7, -1e7, 1e7 + 1e-9],
                        [-1e7, 5.0, 3.0]] + [[float(i), 1e6, -1e6] for i in range(10)], dtype=torch.float64)
    assert_same(pts, 1e-8, 2)
    assert_same(pts, 1.0, 2)


@pytest.mark.parametrize("n", [0, 1, 2])
def test_tiny(n):
    pts = torch.zeros(n, 3)
    for min_samples in (1, 2, 3):
        got = ops.dbscan(pts, 0.5, min_samples)
        assert got.shape == (n,) and got.dtype == torch.int64
        np.testing.assert_array_equal(got.numpy(), reference.dbscan(pts, 0.5, min_samples).numpy())
        if n:
            np.testing.assert_array_equal(got.numpy(), sklearn_labels(pts, 0.5, min_samples))


def test_opcheck():
    pts = torch.rand(64, 3, generator=torch.Generator().manual_seed(0))
    torch.library.opcheck(F.dbscan, (pts, 0.3, 3))
    torch.library.opcheck(F.dbscan, (pts.double(), 0.3, 3))


def test_bad_inputs():
    pts = torch.rand(20, 3)
    bad = pts.clone()
    bad[3, 1] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        ops.dbscan(bad, 0.5, 4)
    with pytest.raises(RuntimeError, match="finite"):
        F.dbscan(bad, 0.5, 4)
    with pytest.raises(ValueError, match="eps"):
        ops.dbscan(pts, 0.0, 4)
    with pytest.raises(ValueError, match="eps"):
        ops.dbscan(pts, float("inf"), 4)
    with pytest.raises(ValueError, match="min_samples"):
        ops.dbscan(pts, 0.5, 0)
    with pytest.raises(RuntimeError, match="eps"):
        F.dbscan(pts, -1.0, 4)
    with pytest.raises(RuntimeError, match="min_samples"):
        F.dbscan(pts, 0.5, 0)
    with pytest.raises(ValueError, match="shape"):
        ops.dbscan(torch.rand(5, 2), 0.5, 4)
    with pytest.raises(TypeError, match="float32"):
        ops.dbscan(torch.ones(5, 3, dtype=torch.int32), 0.5, 4)
    with pytest.raises(RuntimeError, match="float32 or float64"):
        F.dbscan(torch.ones(5, 3, dtype=torch.int32), 0.5, 4)


@pytest.mark.cuda
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cuda_matches_cpu(dtype):
    rng = np.random.default_rng(11)
    from floxels_ext.evaluation.sim import simulate_sequence

    frame = simulate_sequence("crossing", num_frames=1, seed=0).frames[0]
    lidar = torch.as_tensor(frame.points)[~torch.as_tensor(frame.ground)].to(dtype)
    clouds = [blobs(5000, 8, 0.3, dtype, rng), lidar, torch.ones(100, 3, dtype=dtype),
              torch.from_numpy(rng.uniform(0, 3, (3000, 3))).to(dtype), torch.zeros(1, 3, dtype=dtype)]
    for pts in clouds:
        for eps, min_samples in ((0.5, 4), (0.3, 10), (0.2, 1)):
            cpu = F.dbscan(pts, eps, min_samples)
            gpu = F.dbscan(pts.cuda(), eps, min_samples)
            assert gpu.device.type == "cuda" and gpu.dtype == torch.int64
            torch.testing.assert_close(gpu.cpu(), cpu, rtol=0, atol=0)
    assert F.dbscan(torch.zeros(0, 3, dtype=dtype, device="cuda"), 0.5, 4).shape == (0,)
    bad = torch.rand(50, 3, dtype=dtype, device="cuda")
    bad[7, 2] = float("nan")
    with pytest.raises(RuntimeError, match="finite"):
        F.dbscan(bad, 0.5, 4)
    torch.library.opcheck(F.dbscan, (torch.rand(64, 3, device="cuda", dtype=dtype), 0.3, 3))


def lidar_cloud(n, rng, dtype):
    """Lidar-like sweep without the simulator: ground rings, box surfaces, a wall, sparse
    noise and dense blobs near the sensor (thousands of points within eps)."""
    kind = rng.choice(5, size=n, p=[0.35, 0.3, 0.25, 0.07, 0.03])
    pts = np.empty((n, 3))
    m = kind == 0  # rings, one per beam
    r = 2.5 + rng.integers(0, 32, m.sum()) ** 2 * 0.06
    t = rng.uniform(0, 2 * np.pi, m.sum())
    pts[m] = np.c_[r * np.cos(t), r * np.sin(t), np.full(m.sum(), -1.7)] + rng.normal(0, 0.02, (m.sum(), 3))
    m = kind == 1  # objects: box faces
    r, t = rng.uniform(5, 45, 30), rng.uniform(0, 2 * np.pi, 30)
    size = rng.uniform(0.4, 2.0, (30, 3))
    o = rng.integers(0, 30, m.sum())
    local = (rng.uniform(size=(m.sum(), 3)) - 0.5) * size[o]
    side = rng.integers(0, 2, m.sum()).astype(bool)
    local[side, 0] = np.sign(local[side, 0]) * size[o[side], 0] / 2
    local[~side, 1] = np.sign(local[~side, 1]) * size[o[~side], 1] / 2
    pts[m] = np.c_[r[o] * np.cos(t[o]), r[o] * np.sin(t[o]), np.full(m.sum(), -1.2)] + local
    m = kind == 2  # dense near-sensor blobs
    c = np.c_[rng.uniform(-4, 4, (6, 2)), rng.uniform(-1, 0, 6)]
    s = rng.uniform(0.05, 0.3, 6)
    b = rng.integers(0, 6, m.sum())
    pts[m] = c[b] + rng.normal(0, 1, (m.sum(), 3)) * s[b, None]
    m = kind == 3  # a wall
    pts[m] = np.c_[np.full(m.sum(), -20.0), rng.uniform(-30, 30, m.sum()), rng.uniform(-1.7, 2.3, m.sum())]
    m = kind == 4  # sparse noise
    pts[m] = rng.uniform((-60, -60, -2), (60, 60, 4), (m.sum(), 3))
    return torch.from_numpy(pts).to(dtype)


@pytest.mark.cuda
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cuda_lidar_120k_matches_cpu(dtype):
    # The production setting (eps 0.5, min_samples 4) and a stricter one, repeated: the old
    # kernel failed intermittently (cudaErrorInvalidAddressSpace) at this scale.
    rng = np.random.default_rng(5)
    pts = lidar_cloud(120_000, rng, dtype)
    far = pts.clone()
    far[0] = torch.tensor([1e6, -1e6, 3.0], dtype=dtype)  # huge extent: enlarged-cell code path
    for cloud, settings in ((pts, ((0.5, 4), (0.3, 10))), (far, ((0.5, 4),))):
        gpu_cloud = cloud.cuda()
        for eps, min_samples in settings:
            cpu = F.dbscan(cloud, eps, min_samples)
            assert int(cpu.max()) > 10  # many clusters, not a trivial labelling
            for _ in range(3):
                gpu = F.dbscan(gpu_cloud, eps, min_samples)
                torch.cuda.synchronize()
                torch.testing.assert_close(gpu.cpu(), cpu, rtol=0, atol=0)
