"""``floxels run`` hands each scan's sensor position (in the scans' frame) to methods that take
``sensors=`` (Floxels' ``range_mask``): the pose's translation for a sequence of sensor-frame
sweeps, the file's pose for points already in the world frame (datasets); methods without the
keyword are called as before."""

import numpy as np

from floxels_ext import cli, methods
from floxels_ext.evaluation.seqio import save_sequence


def _sweeps(tmp_path, n=7):
    g = np.random.default_rng(0)
    d = tmp_path / "velodyne"
    d.mkdir()
    for i in range(n):
        xy = g.uniform(-20, 20, (500, 2))
        np.c_[xy, g.uniform(-1, 1, len(xy)), np.zeros(len(xy))].astype(np.float32).tofile(d / f"{i:06d}.bin")
    poses = np.tile(np.eye(4)[:3].reshape(1, 12), (n, 1))
    poses[:, 3] = 0.5 * np.arange(n)     # x
    poses[:, 7] = -0.2 * np.arange(n)    # y
    np.savetxt(tmp_path / "poses.txt", poses)
    return d, poses


def test_run_passes_each_scans_sensor_to_methods_that_take_it(tmp_path, monkeypatch):
    d, poses = _sweeps(tmp_path)
    seen = {}

    def est(scans, frames, device, options, callback, times=None, sensors=None):
        assert sensors is not None and len(sensors) == len(scans)
        for f in frames:
            seen[f] = np.asarray(sensors[f], np.float64)
            # the scan's points, moved into the same frame, sit around the sensor like the raw sweep
            callback(f, np.zeros((len(scans[f]), 3), np.float32))

    monkeypatch.setitem(methods._REGISTRY, "fake", methods.Method("fake", "test double", est))
    rc = cli.main(["run", str(d), "--out", str(tmp_path / "out"), "--method", "fake", "--poses",
                   str(tmp_path / "poses.txt"), "--scans", "3", "--device", "cpu", "--no-ground-removal", "-q"])
    assert rc == 0 and sorted(seen) == list(range(7))
    step = np.diff(np.stack([seen[f] for f in range(7)]), axis=0)
    np.testing.assert_allclose(step, np.tile([0.5, -0.2, 0.0], (6, 1)), atol=1e-9)


def test_dataset_stream_passes_the_file_poses(tmp_path, monkeypatch):
    from floxels_ext.evaluation.sim import simulate_sequence

    root = tmp_path / "ds"
    seqs = {}
    for k, scene in enumerate(("urban", "highway")):
        seqs[k] = simulate_sequence(scene, 4, k, beams=16, azimuth_steps=360)
        save_sequence(root / f"s{k}", seqs[k])
    got = []

    def stream(scans, targets, device, options, callback, sensors=None):
        for g, seg in targets:
            got.append((g, seg.lo, np.asarray(sensors[g], np.float64)))
            callback(g, np.zeros((len(scans[g]), 3), np.float32))

    def seq(scans, frames, device, options, callback):
        raise AssertionError("the stream method serves datasets")

    monkeypatch.setitem(methods._REGISTRY, "spy", methods.Method("spy", "test double", seq, estimate_stream=stream))
    rc = cli.main(["run", str(root), "--out", str(tmp_path / "out"), "--method", "spy", "--device", "cpu",
                   "--scans", "3", "--chunk", "4", "-q"])
    assert rc == 0 and len(got) == 8
    by_seg: dict = {}
    for g, lo, s in got:
        by_seg.setdefault(lo, []).append(s)
    for k, (lo, ss) in enumerate(sorted(by_seg.items())):
        want = np.diff(np.stack([fr.pose[:3, 3] for fr in seqs[k].frames]), axis=0)
        np.testing.assert_allclose(np.diff(np.stack(ss), axis=0), want, atol=1e-6)
