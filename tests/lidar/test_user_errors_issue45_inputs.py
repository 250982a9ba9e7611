"""Issue 45 through ``cli.main`` (the ``floxels`` entry point), what a run reads: KISS-ICP
poses computed from other scans (item 1), ``.bin`` column counts (item 2). A fake method
(instant) stands in for Floxels and a fake KISS-ICP (kiss-icp is optional) answers each
scan's true pose."""

import zlib

import numpy as np
import pytest
from cli_doubles import fake, main, simulated  # noqa: F401  (fake: the --method fake fixture)

from floxels_ext.lidar.io.outputs import read_flow_output
from floxels_ext.lidar.preprocess import transform_points

N = 6


@pytest.fixture
def seq():
    return simulated(N, 1)


def _rot_z(a):
    c, s = np.cos(a), np.sin(a)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    return T


class FakeKissIcp:
    """Answers each scan's true sensor-to-world pose, found by the scan's content."""

    def __init__(self):
        self.truth, self.calls = {}, 0

    def add(self, points, pose):
        self.truth[zlib.crc32(np.ascontiguousarray(points[:, :3], np.float32))] = pose

    def __call__(self, scans, progress=None, **settings):
        self.calls += 1
        out = []
        for i, s in enumerate(scans):
            out.append(self.truth[zlib.crc32(np.ascontiguousarray(s, np.float32))])
            if progress:
                progress(i)
        return np.stack(out)


@pytest.fixture
def kiss(monkeypatch):
    from floxels_ext.lidar.preprocess import odometry

    k = FakeKissIcp()
    monkeypatch.setattr(odometry, "kiss_icp_poses", k)
    return k


def _export(seq, d, kiss, mount=np.eye(4)):
    """Sweeps as KITTI .bin in a sensor frame mounted by ``mount`` (a re-export after a
    mounting fix rotates every sweep)."""
    d.mkdir(parents=True, exist_ok=True)
    for i, fr in enumerate(seq.frames):
        pose = fr.pose @ np.linalg.inv(mount)  # the new sensor frame's pose
        p = transform_points(fr.points, np.linalg.inv(pose)).astype(np.float32)
        np.c_[p, np.full(len(p), 0.5)].astype(np.float32).tofile(d / f"{i:06d}.bin")
        kiss.add(p, pose)
    return d


def _run(args, capsys):
    return main(["run", *args, "--device", "cpu"], capsys)


def test_odometry_poses_follow_the_scans_they_were_computed_from(seq, fake, kiss, tmp_path, capsys):
    d, out = _export(seq, tmp_path / "velodyne", kiss), tmp_path / "o"
    args = [d, "--out", out, "--method", "fake", "--odometry", "kiss-icp", "--frames", "2:5"]
    rc, cap = _run(args, capsys)
    assert rc == 0 and kiss.calls == 1, cap.err
    np.testing.assert_allclose(read_flow_output(out / "000003.npz", points=False)["pose"], seq.frames[3].pose,
                               atol=1e-9)
    rc, cap = _run(args, capsys)  # nothing changed: the cached poses, nothing recomputed
    assert rc == 0 and kiss.calls == 1 and "reusing odometry poses" in cap.err and "0 to estimate" in cap.err
    # the example of the issue: the sweeps re-exported rotated by 0.3 rad (a mounting fix)
    mount = _rot_z(0.3)
    _export(seq, d, kiss, mount)
    rc, cap = _run(args, capsys)
    assert rc == 0 and kiss.calls == 2, cap.err
    assert "recomputing the odometry poses" in cap.err and "frame file(s) changed" in cap.err
    assert "3 to estimate" in cap.err  # the resume sees the new poses: every frame again
    for i in (2, 3, 4):
        np.testing.assert_allclose(read_flow_output(out / f"{i:06d}.npz", points=False)["pose"],
                                   seq.frames[i].pose @ np.linalg.inv(mount), atol=1e-9)
    rc, cap = _run([*args, "--force"], capsys)  # --force recomputes the poses too
    assert rc == 0 and kiss.calls == 3 and "recomputing the odometry poses" in cap.err and "--force" in cap.err
    (out / "poses_kiss_icp.json").unlink()  # a cache without its record (an earlier version's)
    rc, cap = _run(args, capsys)
    assert rc == 0 and kiss.calls == 4 and "no poses_kiss_icp.json" in cap.err
    assert "0 to estimate" in cap.err  # the same poses again: the outputs stay


def _xyz_bins(seq, d, shuffle=False):
    """x y z-only float32 .bin frames (sensor frame), sizes cut to a multiple of 4 rows so that
    4 columns also fit (what the issue met); ``shuffle``: rows out of scan order."""
    d.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for i, fr in enumerate(seq.frames):
        p = transform_points(fr.points, np.linalg.inv(fr.pose)).astype(np.float32)
        p = p[np.isfinite(p).all(1)]
        p = p[rng.permutation(len(p))] if shuffle else p
        p[:len(p) // 4 * 4].tofile(d / f"{i:06d}.bin")
    np.savetxt(d.parent / "poses.txt", np.stack([f.pose[:3] for f in seq.frames]).reshape(-1, 12))
    return d


@pytest.mark.parametrize("shuffle", [False, True])
def test_xyz_only_bin_is_refused_not_read_as_xyz_intensity(seq, fake, tmp_path, capsys, shuffle):
    d = _xyz_bins(seq, tmp_path / "velodyne", shuffle)
    args = [d, "--out", tmp_path / "o", "--method", "fake", "--poses", tmp_path / "poses.txt"]
    rc, cap = _run(args, capsys)
    assert rc == 1 and f"{N} failed" in cap.err and not list((tmp_path / "o").glob("*.npz")), cap.err
    assert "000002.bin: its size reads as 4 float32 columns" in cap.err and "pass --bin-columns 3" in cap.err
    assert ("rows look like 3 columns" if not shuffle else "4th column is negative") in cap.err
    rc, cap = _run([*args, "--bin-columns", "3"], capsys)  # what the message says: every frame read right
    assert rc == 0 and f"{N} frame(s) written" in cap.err, cap.err


def test_a_reading_option_that_changes_the_points_makes_the_outputs_stale(seq, fake, tmp_path, capsys):
    # rows out of scan order: --bin-columns 4 cannot be told wrong from them, so the outputs of
    # a misread run exist; rerun with the right count, they must be recomputed, not "already done"
    d = _xyz_bins(seq, tmp_path / "velodyne", shuffle=True)
    args = [d, "--out", tmp_path / "o", "--method", "fake", "--poses", tmp_path / "poses.txt"]
    rc, cap = _run([*args, "--bin-columns", "4"], capsys)
    assert rc == 0, cap.err
    n4 = len(read_flow_output(tmp_path / "o" / "000002.npz", points=False)["flow"])
    rc, cap = _run([*args, "--bin-columns", "3"], capsys)
    assert rc == 0 and f"{N} to estimate" in cap.err and "read with --bin-columns 3 now (--bin-columns 4 then)" in cap.err
    n3 = len(read_flow_output(tmp_path / "o" / "000002.npz", points=False)["flow"])
    assert n3 == n4 * 4 // 3  # every stored point, read as x y z
    rc, cap = _run([*args, "--bin-columns", "3"], capsys)
    assert rc == 0 and "0 to estimate" in cap.err
