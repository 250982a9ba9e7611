"""``floxels run`` keeps each frame's ground returns (the rows preprocessing classed as ground)
and hands them, in the scans' frame, to methods whose options read them (``ground=``,
``Method.uses_ground``: Floxels' ``visibility``); other runs neither keep nor pass them."""

import numpy as np
import pytest

from floxels_ext import cli, methods
from floxels_ext.methods import get_method

N = 5


def _sweeps(tmp_path):
    """Sweeps of a flat road 1.73 m below the sensor and boxes standing on it, sensor frame."""
    g = np.random.default_rng(0)
    d = tmp_path / "velodyne"
    d.mkdir()
    for i in range(N):
        x, y = np.meshgrid(np.arange(-25, 25, 0.4), np.arange(-25, 25, 0.4), indexing="ij")
        road = np.stack([x.ravel(), y.ravel(), np.full(x.size, -1.73)], 1)
        road = road[np.hypot(road[:, 0], road[:, 1]) > 4.0]
        boxes = np.concatenate([g.uniform(-0.5, 0.5, (300, 3)) * [1, 1, 1.5] + [cx, cy, -0.9]
                                for cx, cy in ((10, 3), (-8, 6), (5, -12))])
        pts = np.concatenate([road, boxes])
        np.c_[pts, np.zeros(len(pts))].astype(np.float32).tofile(d / f"{i:06d}.bin")
    poses = np.tile(np.eye(4)[:3].reshape(1, 12), (N, 1))
    poses[:, 3] = 0.5 * np.arange(N)  # x
    np.savetxt(tmp_path / "poses.txt", poses)
    return d


def _run(tmp_path, d, name, *extra):
    return cli.main(["run", str(d), "--out", str(tmp_path / f"out_{name}"), "--method", name, "--poses",
                     str(tmp_path / "poses.txt"), "--scans", "3", "--device", "cpu", "-q", *extra])


def test_run_passes_the_ground_to_methods_whose_options_read_it(tmp_path, monkeypatch):
    d = _sweeps(tmp_path)
    seen = {}

    def est(scans, frames, device, options, callback, times=None, sensors=None, ground=None):
        assert ground is not None and len(ground) == len(scans)
        for f in frames:
            seen[f] = (np.asarray(ground[f]), np.asarray(sensors[f]), np.asarray(scans[f]))
            callback(f, np.zeros((len(scans[f]), 3), np.float32))

    monkeypatch.setitem(methods._REGISTRY, "fake", methods.Method("fake", "test double", est,
                                                                  uses_ground=lambda options: True))
    assert _run(tmp_path, d, "fake") == 0 and sorted(seen) == list(range(N))
    for f, (ground, sensor, scan) in seen.items():
        assert ground.dtype == np.float32 and ground.ndim == 2 and ground.shape[1] == 3 and len(ground) > 1000
        # the road, in the scans' frame: 1.73 m below the sensor (with the boxes' lowest rows,
        # which preprocessing classes as ground too); no road row stays in the scan
        z = ground[:, 2] - sensor[2]
        assert np.isclose(z, -1.73, atol=1e-4).mean() > 0.9 and (z < -1.2).all()
        assert (scan[:, 2] - sensor[2] > -1.72).all()


def test_runs_that_do_not_read_the_ground_get_none(tmp_path, monkeypatch):
    d = _sweeps(tmp_path)
    got = []

    def est(scans, frames, device, options, callback, times=None, sensors=None, ground=None):
        got.append(ground)
        for f in frames:
            callback(f, np.zeros((len(scans[f]), 3), np.float32))

    monkeypatch.setitem(methods._REGISTRY, "nog", methods.Method("nog", "test double", est,
                                                                 uses_ground=lambda options: False))
    assert _run(tmp_path, d, "nog") == 0 and got and all(g is None for g in got)


@pytest.mark.parametrize("options, wants", [({}, False), ({"visibility": True}, True),
                                            ({"num_scans": 11, "visibility": False}, False),
                                            ({"no_such_field": 1}, False)])
def test_floxels_reads_the_ground_with_visibility_only(options, wants):
    assert get_method("floxels").wants_ground(options) is wants


def test_floxels_run_with_the_accurate_preset_uses_the_ground(tmp_path):
    """A pedestrian crossing in front of a road that preprocessing removes: only the road's
    returns in the range images show its old places empty (tests/estimator/test_ground_sight.py),
    so it keeps its motion through ``floxels run --preset accurate`` only if the run hands the
    ground to Floxels (the street of test_run_far_coordinates.py)."""
    from test_run_far_coordinates import WALKER, run_street

    flows, labels = run_street(tmp_path, "street", np.zeros(3), frames=(3, 4))
    flow, mask = flows[3]
    walker = mask & (labels[3] == 2)
    assert walker.sum() > 100
    np.testing.assert_allclose(np.median(flow[walker], 0), [0, WALKER, 0], atol=0.05)


def _dataset(tmp_path, scenes):
    """A dataset of small simulated sequences (points in the world frame, the file's pose)."""
    from floxels_ext.evaluation.seqio import save_sequence
    from floxels_ext.evaluation.sim import simulate_sequence

    root = tmp_path / "ds"
    for k, scene in enumerate(scenes):
        save_sequence(root / f"s{k}", simulate_sequence(scene, 4, k, beams=16, azimuth_steps=360))
    return root


def _run_dataset(tmp_path, root, name, *extra):
    return cli.main(["run", str(root), "--out", str(tmp_path / "out"), "--method", name, "--device", "cpu",
                     "--scans", "3", "-q", *extra])


def test_dataset_stream_passes_the_ground(tmp_path, monkeypatch):
    root = _dataset(tmp_path, ("urban", "highway"))
    got = []

    def stream(scans, targets, device, options, callback, sensors=None, ground=None):
        for g, seg in targets:
            got.append((np.asarray(ground[g]), np.asarray(sensors[g])))
            callback(g, np.zeros((len(scans[g]), 3), np.float32))

    def seq(scans, frames, device, options, callback, sensors=None, ground=None):
        raise AssertionError("the stream method serves datasets")

    monkeypatch.setitem(methods._REGISTRY, "spy", methods.Method("spy", "test double", seq, estimate_stream=stream,
                                                                 uses_ground=lambda options: True))
    assert _run_dataset(tmp_path, root, "spy", "--chunk", "4") == 0 and len(got) == 8
    for ground, sensor in got:
        assert len(ground) > 100
        assert np.median(ground[:, 2] - sensor[2]) < -1.0  # the road, below the sensor


def test_dataset_per_sequence_method_gets_the_ground(tmp_path, monkeypatch):
    root = _dataset(tmp_path, ("urban", "crossing"))
    sizes = []

    def seq(scans, frames, device, options, callback, sensors=None, ground=None):
        for f in frames:
            sizes.append(len(ground[f]))
            callback(f, np.zeros((len(scans[f]), 3), np.float32))

    monkeypatch.setitem(methods._REGISTRY, "per", methods.Method("per", "test double", seq,
                                                                 uses_ground=lambda options: True))
    assert _run_dataset(tmp_path, root, "per") == 0 and len(sizes) == 8 and min(sizes) > 100
