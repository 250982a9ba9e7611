"""The lidar pipeline's CPU ops against their numpy references: lidar_keep_mask (cropping and
ground removal, floxels_ext.lidar.preprocess.masks.preprocess_mask_numpy), rigid_transform, lidar_select,
frame_flow; strided rows (a file's x y z columns, not copied) read as their contiguous copy."""

import numpy as np
import pytest
import torch

import floxels_ext  # noqa: F401
from floxels_ext.lidar.preprocess.masks import preprocess_mask, preprocess_mask_numpy
from floxels_ext.lidar.preprocess.settings import MAX_GROUND_CELLS, Preprocess, _window_cells
from floxels_ext.ops import frame_flow, lidar_keep_mask, lidar_select, rigid_transform


def _scan(seed=0, n=20_000):
    """A street: flat ground with a slope and a kerb, boxes (cars), a wall, NaN rows."""
    g = np.random.default_rng(seed)
    xy = g.uniform(-60, 60, (n, 2))
    z = 0.02 * xy[:, 0] + g.normal(0, 0.03, n)
    z[xy[:, 1] > 8] += 0.15  # kerb
    car = (np.abs(xy[:, 0] - 12) < 2.2) & (np.abs(xy[:, 1] - 3) < 1.0)
    z[car] += g.uniform(0.3, 1.6, car.sum())
    wall = np.abs(xy[:, 1] + 20) < 0.3
    z[wall] += g.uniform(0, 6, wall.sum())
    p = np.c_[xy, z - 1.8].astype(np.float32)
    p[g.choice(n, 30, replace=False)] = np.nan
    p[5] = [np.inf, 0, 0]
    return p


_SETTINGS = [Preprocess(), Preprocess(max_range=None), Preprocess(remove_ground=False), Preprocess(max_height=None),
             Preprocess(ground_max_rise=None), Preprocess(min_range=None, max_range=None, max_height=None,
                                                          remove_ground=False),
             Preprocess(ground_cell=0.3, ground_window=2.0, ground_threshold=0.1, max_range=30.0)]


@pytest.mark.parametrize("k", range(len(_SETTINGS)))
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_keep_mask_equals_the_numpy_reference(k, dtype):
    for seed in (0, 1):
        p = _scan(seed).astype(dtype)
        ref = preprocess_mask_numpy(p, _SETTINGS[k])
        got = preprocess_mask(p, _SETTINGS[k])
        assert got.dtype == np.bool_ and 0 < ref.sum() < len(ref)
        np.testing.assert_array_equal(got, ref)


def test_keep_mask_points_on_the_range_limits():
    """Points exactly at min_range / max_range (hypot == limit) and one ulp either side."""
    r = np.array([3.0, 50.0])
    rows = []
    for lim in r:
        for v in (np.nextafter(lim, 0), lim, np.nextafter(lim, 100)):
            rows.append([v, 0.0, 0.0])
            rows.append([v * 0.6, v * 0.8, 0.0])  # 3-4-5: hypot is exact
    p = np.array(rows, np.float64)
    s = Preprocess(remove_ground=False, max_height=None)
    np.testing.assert_array_equal(preprocess_mask(p, s), preprocess_mask_numpy(p, s))


def test_keep_mask_cells_on_one_line():
    """A one-cell window over points along a diagonal: the plane fit is rank-deficient (lstsq's
    least-norm solution) and the masks still equal the reference."""
    g = np.random.default_rng(3)
    t = np.repeat(np.arange(6, 40, 0.5), 4) + 0.01
    z = -1.8 + 0.05 * t + g.normal(0, 0.05, len(t))
    z[::7] += 1.0
    p = np.c_[t * 0.6, t * 0.6, z].astype(np.float32)  # cells (k, k): colinear
    for w in (0.4, 1.2):
        s = Preprocess(ground_cell=0.5, ground_window=w, ground_threshold=0.2)
        assert _window_cells(w, 0.5) in (1, 3)
        np.testing.assert_array_equal(preprocess_mask(p, s), preprocess_mask_numpy(p, s))


def test_keep_mask_edge_inputs():
    s = Preprocess()
    assert preprocess_mask(np.zeros((0, 3), np.float32), s).shape == (0,)
    assert not preprocess_mask(np.full((4, 3), np.nan, np.float32), s).any()
    one = np.array([[10.0, 0.0, 1.0]], np.float32)
    np.testing.assert_array_equal(preprocess_mask(one, s), preprocess_mask_numpy(one, s))
    with pytest.raises(ValueError, match="ground grid would exceed"):
        lidar_keep_mask(torch.tensor([[0.0, 0, 0], [1500.0, 1500, 0]]), min_range=None, max_range=None,
                        max_height=None, remove_ground=True, ground_cell=0.5, window_cells=17,
                        ground_threshold=0.3, ground_max_rise=0.5, grid_distance=3000.0, max_cells=MAX_GROUND_CELLS)
    with pytest.raises(ValueError, match="window_cells must be odd"):
        lidar_keep_mask(torch.zeros(3, 3), min_range=None, max_range=None, max_height=None, remove_ground=True,
                        ground_cell=0.5, window_cells=4, ground_threshold=0.3, ground_max_rise=None,
                        grid_distance=10.0, max_cells=100)
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        lidar_keep_mask(torch.zeros(3, 2), min_range=None, max_range=None, max_height=None, remove_ground=False,
                        ground_cell=0.5, window_cells=3, ground_threshold=0.3, ground_max_rise=None,
                        grid_distance=10.0, max_cells=100)


def test_rigid_transform_equals_numpy():
    g = np.random.default_rng(1)
    p = (g.normal(0, 30, (5000, 3))).astype(np.float32)
    p[7] = np.nan
    a = 0.7
    T = np.eye(4)
    T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    T[:3, 3] = [1234.5, -987.25, 3.125]
    ref = (p.astype(np.float64) @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
    got = rigid_transform(torch.from_numpy(p), torch.from_numpy(T)).numpy()
    assert got.dtype == np.float32 and np.isnan(got[7]).all()
    ok = np.isfinite(ref).all(1)
    np.testing.assert_allclose(got[ok], ref[ok], rtol=1.2e-7, atol=0)  # float64 sums: at most the last float32 bit
    got64 = rigid_transform(torch.from_numpy(p.astype(np.float64)), torch.from_numpy(T)).numpy()
    np.testing.assert_allclose(got64[ok], p[ok].astype(np.float64) @ T[:3, :3].T + T[:3, 3], rtol=1e-14)
    with pytest.raises(ValueError, match="NaN/inf"):
        rigid_transform(torch.from_numpy(p), torch.full((4, 4), np.nan, dtype=torch.float64))


def test_frame_flow_equals_numpy():
    g = np.random.default_rng(2)
    n = 3000
    mask = g.random(n) < 0.4
    nonfinite = np.flatnonzero(~mask)[:20]
    flow = g.normal(0, 0.1, (mask.sum(), 3)).astype(np.float32)
    a = 1.1
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]], np.float32)
    full, dyn = frame_flow(torch.from_numpy(flow), torch.from_numpy(mask), torch.from_numpy(nonfinite),
                           torch.from_numpy(R), 0.05)
    full, dyn = full.numpy(), dyn.numpy()
    ref = np.zeros((n, 3), np.float32)
    ref[nonfinite] = np.nan
    ref[mask] = flow @ R
    np.testing.assert_allclose(full, ref, rtol=1e-6, atol=1e-7)
    speed = np.linalg.norm(ref, axis=1)
    clear = np.abs(speed - 0.05) > 1e-5
    np.testing.assert_array_equal(dyn[clear], (mask & (speed > 0.05))[clear])
    with pytest.raises(ValueError, match="mask selects"):
        frame_flow(torch.from_numpy(flow[1:]), torch.from_numpy(mask), torch.from_numpy(nonfinite),
                   torch.from_numpy(R), 0.05)


def test_lidar_select_equals_numpy():
    for seed, dtype in ((0, np.float32), (1, np.float64)):
        p = _scan(seed, 5000).astype(dtype)
        mask = np.random.default_rng(seed).random(len(p)) < 0.3
        kept, nonfinite = lidar_select(torch.from_numpy(p), torch.from_numpy(mask))
        assert kept.dtype == torch.from_numpy(p).dtype and kept.is_contiguous()
        np.testing.assert_array_equal(kept.numpy(), p[mask])
        np.testing.assert_array_equal(nonfinite.numpy(), np.flatnonzero(~np.isfinite(p).all(1)))
    kept, nonfinite = lidar_select(torch.zeros(0, 3), torch.zeros(0, dtype=torch.bool))
    assert kept.shape == (0, 3) and nonfinite.shape == (0,)
    with pytest.raises(ValueError, match="mask must have shape"):
        lidar_select(torch.zeros(4, 3), torch.ones(3, dtype=torch.bool))


def test_ops_read_strided_rows():
    """A KITTI .bin read as (N, 4) float32 rows: the ops take its x y z columns as a view."""
    p = _scan(2, 8000)
    rows = np.c_[p, np.arange(len(p), dtype=np.float32)]  # x y z intensity
    view = rows[:, :3]
    assert not view.flags.c_contiguous
    for s in (Preprocess(), Preprocess(remove_ground=False, max_height=None)):
        np.testing.assert_array_equal(preprocess_mask(view, s), preprocess_mask_numpy(p, s))
    mask = preprocess_mask(view)
    kept, nonfinite = lidar_select(torch.from_numpy(view), torch.from_numpy(mask))
    np.testing.assert_array_equal(kept.numpy(), p[mask])
    np.testing.assert_array_equal(nonfinite.numpy(), np.flatnonzero(~np.isfinite(p).all(1)))
    T = np.eye(4)
    T[:3, 3] = [1.5, -2.0, 0.25]
    np.testing.assert_array_equal(rigid_transform(torch.from_numpy(view), torch.from_numpy(T)).numpy(),
                                  rigid_transform(torch.from_numpy(p), torch.from_numpy(T)).numpy())
    col_major = np.asfortranarray(p)  # column strides, as from a transposed (3, N) array
    np.testing.assert_array_equal(preprocess_mask(col_major), preprocess_mask_numpy(p))


def test_lidar_ops_pass_opcheck():
    p = torch.from_numpy(_scan(4, 2000))
    T = torch.eye(4, dtype=torch.float64)
    T[:3, 3] = torch.tensor([1.0, 2.0, 3.0])
    mask = torch.rand(2000) < 0.5
    args = (p, 3.0, 50.0, 4.0, True, 0.5, 17, 0.3, 0.5, 58.0, MAX_GROUND_CELLS, 1.0, 20.0)
    for op, a in ((torch.ops.floxels.lidar_keep_mask, args), (torch.ops.floxels.lidar_point_classes, args),
                  (torch.ops.floxels.rigid_transform, (p, T)),
                  (torch.ops.floxels.lidar_select, (p, mask)),
                  (torch.ops.floxels.frame_flow, (torch.randn(int(mask.sum()), 3), mask,
                                                  torch.tensor([0, 3]), torch.eye(3), 0.05))):
        torch.library.opcheck(op, a, test_utils=("test_schema", "test_faketensor"))
