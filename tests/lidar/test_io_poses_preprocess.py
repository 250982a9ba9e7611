"""Pose files, ego-motion transforms, ground removal / cropping, odometry adapter, accumulation."""

import math

import numpy as np
import pytest

from floxels_ext.lidar.viz.accumulate import accumulate
from floxels_ext.lidar.io import MissingDependencyError, PoseFormatError, read_poses
from floxels_ext.lidar.io.poses import check_poses, match_timestamps, quat_to_matrix, read_av2_poses
from floxels_ext.lidar.preprocess import (Preprocess, crop_mask, ground_mask, ground_surface, preprocess_mask,
                                          preprocess_mask_numpy, relative_pose, transform_points)


def _rot_z(a, t=(0, 0, 0)):
    T = np.eye(4)
    T[:2, :2] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
    T[:3, 3] = t
    return T


def _poses(n=4):
    return np.stack([_rot_z(0.1 * i, (2.0 * i, 0.5 * i, 0.01 * i)) for i in range(n)])


# ----------------------------------------------------------------------------- poses
def test_kitti_txt_16_values_npy_npz(tmp_path):
    P = _poses()
    np.savetxt(tmp_path / "poses.txt", P[:, :3].reshape(4, 12))
    np.testing.assert_allclose(read_poses(tmp_path / "poses.txt"), P, atol=1e-12)
    (tmp_path / "p16.txt").write_text("# comment\n\n" + "\n".join(" ".join(map(repr, T.ravel().tolist())) for T in P))
    np.testing.assert_allclose(read_poses(tmp_path / "p16.txt"), P)
    np.save(tmp_path / "p.npy", P)
    np.testing.assert_allclose(read_poses(tmp_path / "p.npy"), P)
    np.savez(tmp_path / "p.npz", poses=P[:, :3])
    np.testing.assert_allclose(read_poses(tmp_path / "p.npz"), P)


def test_tum_and_kitti_calib(tmp_path):
    P = _poses(3)
    # TUM: t tx ty tz qx qy qz qw (rotation about z by a: q = (cos a/2, 0, 0, sin a/2))
    rows = [[i, *P[i, :3, 3], 0, 0, math.sin(0.05 * i), math.cos(0.05 * i)] for i in range(3)]
    np.savetxt(tmp_path / "tum.txt", rows)
    np.testing.assert_allclose(read_poses(tmp_path / "tum.txt"), P, atol=1e-12)
    Tr = _rot_z(0.3, (0.1, -0.2, 0.3))
    cam = np.linalg.inv(np.linalg.inv(Tr)) @ P @ np.linalg.inv(Tr)  # P_cam = Tr P_velo Tr^-1
    np.savetxt(tmp_path / "cam.txt", cam[:, :3].reshape(3, 12))
    (tmp_path / "calib.txt").write_text("P0: " + " ".join(["0"] * 12) + "\nTr: " + " ".join(map(repr, Tr[:3].ravel().tolist())))
    np.testing.assert_allclose(read_poses(tmp_path / "cam.txt", calib=tmp_path / "calib.txt"), P, atol=1e-9)


def test_pose_errors_name_the_file(tmp_path):
    (tmp_path / "a.txt").write_text("1 2 3\n")
    with pytest.raises(PoseFormatError, match=r"a\.txt:1: 3 values"):
        read_poses(tmp_path / "a.txt")
    (tmp_path / "b.txt").write_text(" ".join(["1"] * 12) + "\n")
    with pytest.raises(PoseFormatError, match=r"b\.txt.*not a rigid transform"):
        read_poses(tmp_path / "b.txt")
    np.save(tmp_path / "c.npy", np.zeros((3, 4, 3)))
    with pytest.raises(PoseFormatError, match=r"c\.npy.*shape"):
        read_poses(tmp_path / "c.npy")
    P = _poses(2)
    P[1, 0, 3] = np.nan
    np.save(tmp_path / "d.npy", P)
    with pytest.raises(PoseFormatError, match=r"d\.npy: pose 1 has NaN"):
        read_poses(tmp_path / "d.npy")
    (tmp_path / "e.txt").write_text("x y z\n")
    with pytest.raises(PoseFormatError, match=r"e\.txt:1: not a list of numbers"):
        read_poses(tmp_path / "e.txt")
    with pytest.raises(PoseFormatError, match="does not exist"):
        read_poses(tmp_path / "none.txt")
    assert check_poses(np.eye(4), "x").shape == (1, 4, 4)


def test_empty_or_foreign_pose_and_calib_files_are_named(tmp_path):
    # an empty poses .npy raised EOFError (a traceback from floxels run); a text file saved as
    # .npy was "pickled (object) data"; a missing --calib a bare "[Errno 2] ..."
    (tmp_path / "p.npy").write_bytes(b"")
    with pytest.raises(PoseFormatError, match=r"p\.npy: cannot read poses \(empty file"):
        read_poses(tmp_path / "p.npy")
    (tmp_path / "q.npz").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(PoseFormatError, match=r"q\.npz: cannot read poses \(not a \.npz file") as e:
        read_poses(tmp_path / "q.npz")
    assert "pickle" not in str(e.value)
    np.save(tmp_path / "ok.npy", _poses(2))
    with pytest.raises(PoseFormatError, match=r"none\.txt: calib file does not exist"):
        read_poses(tmp_path / "ok.npy", calib=tmp_path / "none.txt")
    (tmp_path / "bin.txt").write_bytes(b"\xff\xfe\x00\x81")
    with pytest.raises(PoseFormatError, match=r"bin\.txt: not a text file"):
        read_poses(tmp_path / "ok.npy", calib=tmp_path / "bin.txt")


def test_av2_poses_and_timestamp_matching(tmp_path):
    pa = pytest.importorskip("pyarrow")
    feather = pytest.importorskip("pyarrow.feather")
    P = _poses(3)
    q = [[math.cos(0.05 * i), 0, 0, math.sin(0.05 * i)] for i in range(3)]
    np.testing.assert_allclose(quat_to_matrix(np.array(q)), P[:, :3, :3], atol=1e-12)
    times = np.array([300, 100, 200], np.int64) * 1_000_000
    t = pa.table({"timestamp_ns": times[[1, 2, 0]], "qw": [x[0] for x in q], "qx": [0.0] * 3, "qy": [0.0] * 3,
                  "qz": [x[3] for x in q], "tx_m": P[:, 0, 3], "ty_m": P[:, 1, 3], "tz_m": P[:, 2, 3]})
    feather.write_feather(t, str(tmp_path / "city_SE3_egovehicle.feather"))
    ts, poses = read_av2_poses(tmp_path / "city_SE3_egovehicle.feather")
    got = match_timestamps(ts, poses, [100_000_000, 200_000_001, 300_000_000], "f")
    np.testing.assert_allclose(got, P, atol=1e-12)
    with pytest.raises(PoseFormatError, match="no pose within"):
        match_timestamps(ts, poses, [150_000_000], "f")


# ----------------------------------------------------------------------------- transforms
def test_ego_motion_round_trip():
    rng = np.random.default_rng(0)
    P = _poses(3)
    world = rng.normal(scale=20, size=(50, 3))
    # the same static points seen from each sensor pose, then brought into frame 2's coordinates
    local = [transform_points(world, np.linalg.inv(T)) for T in P]
    for k in range(3):
        back = transform_points(local[k], relative_pose(P[k], P[2]))
        np.testing.assert_allclose(back, local[2], atol=1e-4)
    nan = transform_points(np.array([[np.nan, 0, 0]]), P[1])
    assert np.isnan(nan).any()


# ----------------------------------------------------------------------------- ground / crop
def _sim_frame(scene, seed):
    from floxels_ext.evaluation.sim import simulate_sequence

    fr = simulate_sequence(scene, 1, seed, small=True).frames[0]
    return fr, transform_points(fr.points, np.linalg.inv(fr.pose))


@pytest.mark.parametrize("scene", ["urban", "parking", "highway"])
def test_ground_removal_quality_on_sim(scene):
    fr, ps = _sim_frame(scene, 1)
    g = ground_mask(ps)
    recall = (g & fr.ground).sum() / fr.ground.sum()
    above = ~fr.ground & (fr.points[:, 2] > 0.4)  # clearly above the (flat, z = 0) simulated ground
    kept = (~g & above).sum() / above.sum()
    assert recall >= 0.95, recall
    assert kept >= 0.97, kept


def test_ground_removal_on_a_slope():
    fr, ps = _sim_frame("crossing", 2)
    a = math.radians(4)  # tilt the whole scene: 7 % grade
    R = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    g = ground_mask(ps @ R.T)
    assert (g & fr.ground).sum() / fr.ground.sum() >= 0.95
    above = ~fr.ground & (fr.points[:, 2] > 0.4)
    assert (~g & above).sum() / above.sum() >= 0.95


def test_crop_and_preprocess_settings():
    pts = np.array([[1, 0, 0], [10, 0, 0], [60, 0, 0], [10, 0, 5], [np.nan, 0, 0]], np.float32)
    np.testing.assert_array_equal(crop_mask(pts), [0, 1, 0, 0, 0])
    np.testing.assert_array_equal(crop_mask(pts, min_range=None, max_range=None, max_height=None), [1, 1, 1, 1, 0])
    np.testing.assert_array_equal(crop_mask(pts, ground_height=2.0), [0, 1, 0, 1, 0])
    keep = preprocess_mask(pts, Preprocess(remove_ground=False, max_height=None))
    np.testing.assert_array_equal(keep, [0, 1, 0, 1, 0])
    with pytest.raises(ValueError, match="min_range"):
        Preprocess(min_range=60, max_range=50)
    with pytest.raises(ValueError, match="ground_window"):
        Preprocess(ground_window=0)


_SETTINGS = [Preprocess(), Preprocess(max_range=None), Preprocess(remove_ground=False),
             Preprocess(max_height=None, ground_max_rise=None), Preprocess(min_range=None, ground_window=3.0)]


@pytest.mark.parametrize("k", range(len(_SETTINGS)))
def test_op_and_torch_preprocessing_give_the_numpy_masks(k):
    """The compiled op (the default) and the GPU path (run here on CPU tensors) must select
    exactly the numpy reference's points."""
    from floxels_ext.lidar.preprocess.masks_torch import preprocess_mask_torch

    for scene, seed in (("urban", 3), ("parking", 4)):
        _, ps = _sim_frame(scene, seed)
        ps = ps.copy()
        ps[3] = np.nan
        ps[4] = [1e30, 2.0, 0.0]
        ps[5] = [900.0, -40.0, -3.0]
        a = preprocess_mask_numpy(ps, _SETTINGS[k])
        assert 0 < a.sum() < len(a)
        np.testing.assert_array_equal(preprocess_mask_torch(ps, _SETTINGS[k], "cpu"), a)
        np.testing.assert_array_equal(preprocess_mask(ps, _SETTINGS[k]), a)
        np.testing.assert_array_equal(preprocess_mask(ps.astype(np.float64), _SETTINGS[k]), a)


@pytest.mark.cuda
def test_torch_preprocessing_on_cuda_gives_the_numpy_masks():
    import torch

    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    from floxels_ext.lidar.preprocess.masks_torch import preprocess_mask_torch

    _, ps = _sim_frame("urban", 6)
    for st in _SETTINGS:
        np.testing.assert_array_equal(preprocess_mask_torch(ps, st, "cuda"), preprocess_mask_numpy(ps, st))


def test_stray_far_points_neither_crash_nor_change_the_near_masks():
    """Issue 17.1: rows at |x| ~ 1e30 crashed ground removal; a point 1.5 km away made it
    quadratic in the extent and changed the mask of near points. The crop comes first now."""
    import time

    _, ps = _sim_frame("urban", 5)
    base = preprocess_mask(ps)
    bad = np.concatenate([ps, [[1e30, 0, 0], [-1e30, 1e30, 5], [1500.0, 20.0, -1.0]]]).astype(np.float32)
    t0 = time.perf_counter()
    m = preprocess_mask(bad)
    assert time.perf_counter() - t0 < 2.0
    np.testing.assert_array_equal(m[:len(ps)], base)
    np.testing.assert_array_equal(preprocess_mask_numpy(bad), m)
    assert not m[len(ps):].any()
    m2 = preprocess_mask(bad, Preprocess(max_range=None))  # no range crop: the grid stays bounded
    assert not m2[len(ps):].any()
    with pytest.raises(ValueError, match="ground grid"):
        ground_surface(bad, max_distance=None)  # unbounded on request: a clear error, not 1e30 cells


# ----------------------------------------------------------------------------- odometry
def test_odometry_missing_package_message(monkeypatch):
    import importlib

    from floxels_ext.lidar.preprocess import odometry

    real = importlib.import_module

    def fake(name, *a):
        if name.startswith("kiss_icp"):
            raise ImportError("No module named 'kiss_icp'")
        return real(name, *a)

    monkeypatch.setattr(importlib, "import_module", fake)
    with pytest.raises(MissingDependencyError, match=r"floxels_ext\[odometry\].*pip install kiss-icp"):
        odometry.kiss_icp_poses([np.zeros((5, 3))])


def test_odometry_kiss_icp_if_installed():
    pytest.importorskip("kiss_icp")
    from floxels_ext.lidar.preprocess.odometry import kiss_icp_poses

    rng = np.random.default_rng(0)
    # a box-shaped room seen from a sensor moving 0.5 m per frame along x
    walls = np.concatenate([np.c_[rng.uniform(-20, 20, 3000), np.full(3000, s * 8), rng.uniform(-1, 3, 3000)]
                            for s in (-1, 1)] + [np.c_[np.full(2000, s * 20), rng.uniform(-8, 8, 2000),
                                                       rng.uniform(-1, 3, 2000)] for s in (-1, 1)]
                           + [np.c_[rng.uniform(-20, 20, 4000), rng.uniform(-8, 8, 4000), np.full(4000, -1.0)]])
    scans = [walls - [0.5 * i, 0, 0] for i in range(5)]
    P = kiss_icp_poses(scans, max_range=50)
    np.testing.assert_allclose(P[:, 0, 3], 0.5 * np.arange(5), atol=0.1)


# ----------------------------------------------------------------------------- accumulation
def test_accumulate_constant_velocity_and_chain():
    rng = np.random.default_rng(0)
    obj = rng.uniform(-1, 1, size=(200, 3))
    v = np.array([1.0, 0.5, 0.0])  # metres per frame
    pts = [obj + k * v for k in range(5)]
    flows = [np.tile(v, (200, 1)) for _ in range(5)]
    for mode in ("constant-velocity", "chain"):
        out, src = accumulate(pts, flows, 2, mode=mode)
        assert out.shape == (1000, 3) and np.bincount(src).tolist() == [200] * 5
        for k in range(5):
            np.testing.assert_allclose(out[src == k], pts[2], atol=1e-5, err_msg=f"{mode} {k}")
    with pytest.raises(ValueError, match="mode"):
        accumulate(pts, flows, 2, mode="nope")
    with pytest.raises(ValueError, match="flow has shape"):
        accumulate(pts, [f[:10] for f in flows], 2)
