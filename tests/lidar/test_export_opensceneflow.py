"""``floxels export --format opensceneflow``: write, then read back as OpenSceneFlow's trainer does.

OpenSceneFlow's reader is not installable (a research repository, not a package), so
``_read_like_hdf5dataset`` below reproduces what it reads, from KTH-RPL/OpenSceneFlow commit
848bf86fe4399596bd236226ae8d2a6461a17ead: ``src/dataset.py`` ``HDF5Dataset.__init__`` (the
index ``index_total.pkl``; ``index_flow.pkl`` when a scene's frames lack ``flow``) and
``__getitem__`` (``f[key]['lidar'][:][:, :3]``, ``ground_mask``, ``pose``, the next entry of the
index as frame 1, ``flow``, ``flow_is_valid``, ``ego_motion``), ``collate_fn_pad`` (points and
flow of the ``ground_mask`` rows dropped), ``src/models/basic/__init__.py`` ``cal_pose0to1``
(``inv(pose1) @ pose0`` in float64) and ``src/trainer.py`` (the label the loss sees: ``flow``
minus the ego-motion flow of ``cal_pose0to1``). The runs use a fake method with a known answer
(a constant world-frame velocity), so the exported labels are checked exactly."""

from __future__ import annotations

import pickle
import shutil

import numpy as np
import pytest

from floxels_ext import cli, methods
from floxels_ext.evaluation.seqio import save_sequence
from floxels_ext.lidar.preprocess import transform_points

h5py = pytest.importorskip("h5py")

N_FRAMES = 4
V_WORLD = np.array([0.3, -0.2, 0.05], np.float32)  # the fake method's answer, world axes, per frame


@pytest.fixture(scope="module")
def seq():
    from floxels_ext.evaluation.sim import simulate_sequence

    return simulate_sequence("crossing", N_FRAMES, 1, beams=16, azimuth_steps=360)


@pytest.fixture
def fake(monkeypatch):
    def est(scans, frames, device, options, callback):
        for f in frames:
            callback(f, np.tile(V_WORLD, (len(scans[f]), 1)))

    monkeypatch.setitem(methods._REGISTRY, "fake", methods.Method("fake", "test double", est))


def _sensor_frames(seq, d, name="{i:06d}.npy"):
    """The frames in their sensor frames (.npy) and a poses file: a run in native coordinates."""
    d.mkdir(parents=True)
    for i, fr in enumerate(seq.frames):
        p = transform_points(fr.points, np.linalg.inv(fr.pose)).astype(np.float32)
        if i == 1:
            p[3] = np.nan  # a NaN row keeps its place
        np.save(d / name.format(i=i), p)
    poses = d.parent / f"{d.name}_poses.txt"
    np.savetxt(poses, np.stack([f.pose[:3] for f in seq.frames]).reshape(-1, 12))
    return d, poses


def _run(*args):
    assert cli.main(["run", *map(str, args), "--method", "fake", "--device", "cpu", "-q"]) == 0


def _export(run, out):
    return cli.main(["export", str(run), str(out), "--format", "opensceneflow"])


def _cal_pose0to1(pose0, pose1):
    pose0, pose1 = pose0.astype(np.float64), pose1.astype(np.float64)
    return np.linalg.inv(pose1) @ pose0


def _read_like_hdf5dataset(directory):
    """Every training sample as OpenSceneFlow's HDF5Dataset + collate_fn_pad make it (module doc)."""
    with open(directory / "index_total.pkl", "rb") as fh:
        index = pickle.load(fh)
    bounds = {}
    for k, (scene, _) in enumerate(index):
        bounds.setdefault(scene, [k, k])[1] = k
    samples = []
    for k, (scene, key) in enumerate(index):
        if k == bounds[scene][1]:
            continue  # the dataset clamps to max_index - 1: the last frame is only ever frame 1
        nxt = index[k + 1][1]
        with h5py.File(directory / f"{scene}.h5", "r") as f:
            g0, g1 = f[key], f[nxt]
            s = {"scene_id": scene, "timestamp": key, "pc0": g0["lidar"][:][:, :3], "gm0": g0["ground_mask"][:],
                 "pose0": g0["pose"][:], "pc1": g1["lidar"][:][:, :3], "gm1": g1["ground_mask"][:],
                 "pose1": g1["pose"][:]}
            for name in ("ego_motion", "flow", "flow_is_valid", "flow_category_indices"):
                if name in g0:
                    s[name] = g0[name][:]
        s["pc0_kept"], s["flow_kept"] = s["pc0"][~s["gm0"]], s["flow"][~s["gm0"]]  # collate_fn_pad
        T = _cal_pose0to1(s["pose0"], s["pose1"])
        s["pose_flow"] = s["pc0_kept"] @ T[:3, :3].T + T[:3, 3] - s["pc0_kept"]
        s["gt_flow"] = s["flow_kept"] - s["pose_flow"]  # what trainer.loss_calculator gives the loss
        samples.append(s)
    return index, samples


def test_round_trip_native_frames(seq, fake, tmp_path):
    d, poses = _sensor_frames(seq, tmp_path / "scans")
    _run(d, "--poses", poses, "--out", tmp_path / "run")
    assert _export(tmp_path / "run", tmp_path / "h5") == 0
    assert sorted(p.name for p in (tmp_path / "h5").iterdir()) == ["index_flow.pkl", "index_total.pkl", "run.h5"]
    index, samples = _read_like_hdf5dataset(tmp_path / "h5")
    assert index == [["run", str(i)] for i in range(N_FRAMES)]
    with open(tmp_path / "h5" / "index_flow.pkl", "rb") as fh:
        assert pickle.load(fh) == index[:-1]
    assert [s["timestamp"] for s in samples] == [str(i) for i in range(N_FRAMES - 1)]
    from floxels_ext.lidar.io.outputs import read_flow_output

    P0 = seq.frames[0].pose
    for i, s in enumerate(samples):
        out = read_flow_output(tmp_path / "run" / f"{i:06d}.npz")
        # the layout of create_group_data: dtypes and shapes; no classes for pseudo-labels
        assert s["pc0"].dtype == np.float32 and s["flow"].dtype == np.float32 and s["pose0"].dtype == np.float32
        assert s["gm0"].dtype == np.bool_ and s["flow_is_valid"].dtype == np.bool_ and s["ego_motion"].shape == (4, 4)
        assert "flow_category_indices" not in s
        np.testing.assert_array_equal(s["pc0"], out["points"])  # the frame's points, NaN rows included
        np.testing.assert_array_equal(s["gm0"], ~out["mask"])
        np.testing.assert_array_equal(s["flow_is_valid"], out["mask"])
        assert np.isfinite(s["flow"]).all()
        # poses relative to the scene's first frame; the ego motion the trainer computes from them
        np.testing.assert_allclose(s["pose0"], np.linalg.inv(P0) @ seq.frames[i].pose, atol=1e-5)
        np.testing.assert_allclose(_cal_pose0to1(s["pose0"], s["pose1"]), out["ego_motion"], atol=1e-5)
        # the label: each kept point moves by V_WORLD in the world, i.e. by R0^T V_WORLD in the
        # scene's frame (poses relative to frame 0): pose1 (p + flow) = pose0 p + R0^T V
        moved = s["pc0_kept"] + s["flow_kept"]
        lhs = moved @ s["pose1"][:3, :3].T.astype(np.float64) + s["pose1"][:3, 3]
        rhs = s["pc0_kept"] @ s["pose0"][:3, :3].T.astype(np.float64) + s["pose0"][:3, 3] + V_WORLD @ P0[:3, :3]
        np.testing.assert_allclose(lhs, rhs, atol=2e-4)
        # what the loss sees: the object motion in frame 1's axes
        np.testing.assert_allclose(s["gt_flow"], np.tile(V_WORLD @ seq.frames[i + 1].pose[:3, :3],
                                                         (len(s["gt_flow"]), 1)), atol=2e-4)
    with h5py.File(tmp_path / "h5" / "run.h5", "r") as f:
        assert "flow" not in f[str(N_FRAMES - 1)] and "ego_motion" not in f[str(N_FRAMES - 1)]


def test_world_frame_run(seq, fake, tmp_path):
    """A run over world-frame points (floxels simulate layout): identity poses, the flow as is."""
    save_sequence(tmp_path / "sim", seq)
    _run(tmp_path / "sim", "--out", tmp_path / "run")
    assert _export(tmp_path / "run", tmp_path / "h5") == 0
    _, samples = _read_like_hdf5dataset(tmp_path / "h5")
    assert len(samples) == N_FRAMES - 1
    for s in samples:
        np.testing.assert_array_equal(s["pose0"], np.eye(4, dtype=np.float32))
        np.testing.assert_allclose(s["gt_flow"], np.tile(V_WORLD, (len(s["gt_flow"]), 1)), atol=1e-6)


def test_dataset_run_gives_one_scene_per_sequence(seq, fake, tmp_path):
    root = tmp_path / "data"
    save_sequence(root / "a", seq)
    save_sequence(root / "b", seq)
    _run(root, "--out", tmp_path / "run")
    assert _export(tmp_path / "run", tmp_path / "h5") == 0
    index, _ = _read_like_hdf5dataset(tmp_path / "h5")
    assert index == [[s, str(i)] for s in ("a", "b") for i in range(N_FRAMES)]


def test_a_second_export_into_the_same_out_keeps_the_first_scenes_indexed(seq, fake, tmp_path, capsys):
    # the index files were replaced: the first run's .h5 stayed but the trainer no longer saw it
    save_sequence(tmp_path / "sim", seq)
    _run(tmp_path / "sim", "--out", tmp_path / "a")
    _run(tmp_path / "sim", "--out", tmp_path / "b")
    assert _export(tmp_path / "a", tmp_path / "h5") == 0 and _export(tmp_path / "b", tmp_path / "h5") == 0
    assert "also keep the 1 scene(s) already in" in capsys.readouterr().out
    index, samples = _read_like_hdf5dataset(tmp_path / "h5")
    assert index == [[s, str(i)] for s in ("a", "b") for i in range(N_FRAMES)] and len(samples) == 2 * (N_FRAMES - 1)
    assert _export(tmp_path / "a", tmp_path / "h5") == 0  # a re-export replaces its own entries, once
    assert _read_like_hdf5dataset(tmp_path / "h5")[0] == [[s, str(i)] for s in ("b", "a") for i in range(N_FRAMES)]
    (tmp_path / "h5" / "b.h5").unlink()  # a scene whose file is gone leaves the index
    assert _export(tmp_path / "a", tmp_path / "h5") == 0
    assert _read_like_hdf5dataset(tmp_path / "h5")[0] == [["a", str(i)] for i in range(N_FRAMES)]


def test_refusals(seq, fake, tmp_path, capsys):
    d, poses = _sensor_frames(seq, tmp_path / "scans")
    _run(d, "--poses", poses, "--out", tmp_path / "run")

    def refused(run, says):
        out = tmp_path / "h5"
        capsys.readouterr()  # what the runs printed
        rc = _export(run, out)
        err = capsys.readouterr().err
        assert rc == 2 and err.startswith("floxels: error: ") and says in err, err
        assert not out.exists() or not any(out.iterdir())

    gap = tmp_path / "gap"
    shutil.copytree(tmp_path / "run", gap)
    (gap / "000001.npz").unlink()  # a failed frame in the middle
    refused(gap, "frame 000001 (after 000000) has no output")
    # frame names that are no numbers, and no timestamps: no keys for the groups
    d2, poses2 = _sensor_frames(seq, tmp_path / "named", name="scan_{i}.npy")
    _run(d2, "--poses", poses2, "--out", tmp_path / "run2")
    refused(tmp_path / "run2", "is not a number")
    # ground truth given by mistake
    save_sequence(tmp_path / "sim", seq)
    refused(tmp_path / "sim", "not an output of 'floxels run'")
    (tmp_path / "empty").mkdir()
    refused(tmp_path / "empty", "holds no outputs")
