"""``floxels run DATASET``: finding the sequences of a dataset root or list file, the mirrored output
tree, cutting sequences into tasks, and the local (no Ray) dataset run."""

from pathlib import Path

import numpy as np
import pytest

from floxels_ext import cli
from floxels_ext.errors import CLIError
from floxels_ext.lidar.dataset.tasks import SequenceSpec, discover_dataset, plan_tasks
from floxels_ext.lidar.pipeline.run_args import parse_frame_range
from floxels_ext.evaluation.seqio import save_sequence

FAST = ["--device", "cpu", "--scans", "3", "--chunk", "2", "--method", "fake"]


@pytest.fixture(autouse=True)
def fake(monkeypatch):
    """An instant method (these tests check the plumbing; test_ray.py runs Floxels itself): the flow
    of a point is a function of its world position, so a wrong pose shows."""
    from floxels_ext import methods

    def est(scans, frames, device, options, callback):
        for f in frames:
            callback(f, np.asarray(scans[f], np.float32) * 0.01)

    monkeypatch.setitem(methods._REGISTRY, "fake", methods.Method("fake", "test double", est))


def _touch(p, data=b""):
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_bytes(data)


def _kitti_bin(seq, d, nan_row=True):
    """Frames of ``seq`` as KITTI velodyne .bin files in their sensor frames, + KITTI poses."""
    from floxels_ext.lidar.preprocess import transform_points

    d.mkdir(parents=True, exist_ok=True)
    for i, fr in enumerate(seq.frames):
        p = transform_points(fr.points, np.linalg.inv(fr.pose))
        if nan_row and i == 1:
            p[3] = np.nan
        np.c_[p, np.zeros(len(p))].astype(np.float32).tofile(d / f"{i:06d}.bin")
    return np.stack([f.pose[:3] for f in seq.frames]).reshape(-1, 12)


def test_discover_tree_kitti_av2_sim(tmp_path):
    root = tmp_path / "data"
    _touch(root / "kitti/sequences/00/velodyne/000000.bin")
    _touch(root / "kitti/sequences/00/calib.txt")
    _touch(root / "kitti/sequences/00/image_2/000000.png")
    _touch(root / "kitti/sequences/01/velodyne/000000.bin")
    _touch(root / "kitti/poses/00.txt")                   # 01 has no poses (KITTI test sequences)
    _touch(root / "av2/val/log-a/sensors/lidar/1.feather")
    _touch(root / "av2/val/log-a/map/ground.npy")          # not a sequence of its own
    _touch(root / "sim/s0/000000.npz")
    _touch(root / "out/old/000000.npz")                    # the output tree is never read as input
    specs = discover_dataset(root, root / "out")
    assert [s.rel.as_posix() for s in specs] == ["av2/val/log-a", "kitti/sequences/00/velodyne",
                                                "kitti/sequences/01/velodyne", "sim/s0"]
    k0, k1 = specs[1], specs[2]
    assert k0.poses == root.resolve() / "kitti/poses/00.txt" and k0.calib.name == "calib.txt"
    assert k1.poses is None and k1.calib is None
    sel = discover_dataset(root, root / "out", ["kitti/*/0[0-9]/*"])
    assert [s.rel.as_posix() for s in sel] == ["kitti/sequences/00/velodyne", "kitti/sequences/01/velodyne"]
    assert discover_dataset(root / "sim/s0") is None                # one sequence: the plain run
    with pytest.raises(CLIError, match="selects none"):
        discover_dataset(root, None, ["nope/*"])
    (tmp_path / "empty/sub").mkdir(parents=True)
    with pytest.raises(CLIError, match="no lidar frames"):
        discover_dataset(tmp_path / "empty")


def test_list_file(tmp_path):
    _touch(tmp_path / "a/s1/0.bin")
    _touch(tmp_path / "b/s2/0.bin")
    _touch(tmp_path / "b/s2.txt")
    lst = tmp_path / "list.txt"
    lst.write_text("# two sequences\na/s1\n\nb/s2 --poses b/s2.txt  # with its poses\n")
    specs = discover_dataset(lst)
    assert [s.rel.as_posix() for s in specs] == ["a/s1", "b/s2"]
    assert specs[0].poses is None and specs[1].poses == (tmp_path / "b/s2.txt").resolve()
    lst.write_text("a/s1 --pose x\n")
    with pytest.raises(CLIError, match=r"list.txt:1: expected"):
        discover_dataset(lst)
    lst.write_text("a/s1\nmissing/dir\n")
    with pytest.raises(CLIError, match=r"list.txt:2: .*missing/dir does not exist"):
        discover_dataset(lst)
    lst.write_text("a/s1 --calib nope.txt\n")
    with pytest.raises(CLIError, match="--calib .*nope.txt does not exist"):
        discover_dataset(lst)


def test_frame_range_and_task_cuts(tmp_path):
    assert parse_frame_range(None, 10) == (0, 10)
    assert parse_frame_range("2:", 10) == (2, 10) and parse_frame_range("-3:", 10) == (7, 10)
    with pytest.raises(CLIError):
        parse_frame_range("5:2", 10)
    (tmp_path / "s").mkdir()
    for i in range(11):
        np.save(tmp_path / f"s/{i}.npy", np.zeros((4, 3), np.float32))
    assert discover_dataset(tmp_path / "s", "o") is None  # one sequence
    args = cli.build_parser().parse_args(["run", str(tmp_path / "s"), "--out", "o", "--no-ego-motion",
                                          "--frames", "1:"])
    tasks, problems = plan_tasks([SequenceSpec(tmp_path / "s", Path("."))], Path("o"), args, task_frames=3,
                                 align=2)
    assert not problems
    assert [(t.start, t.stop) for t in tasks] == [(1, 5), (5, 9), (9, 11)]   # 3 rounded up to 4 = 2 batches
    assert tasks[0].names == ["1", "2", "3", "4"]


@pytest.fixture(scope="module")
def kitti_tree(tmp_path_factory):
    from floxels_ext.evaluation.sim import simulate_sequence

    root = tmp_path_factory.mktemp("kitti")
    for k, seed in enumerate((0, 1)):
        seq = simulate_sequence("crossing", 4, seed, beams=16, azimuth_steps=360)
        poses = _kitti_bin(seq, root / f"sequences/{k:02d}/velodyne")
        (root / "poses").mkdir(exist_ok=True)
        np.savetxt(root / f"poses/{k:02d}.txt", poses)
    save_sequence(root / "sim" / "s0", simulate_sequence("urban", 3, 2, beams=16, azimuth_steps=360))
    return root


def test_local_dataset_run_mirrors_tree_and_equals_plain_run(kitti_tree, tmp_path, capsys):
    out = tmp_path / "flow"
    assert cli.main(["run", str(kitti_tree), "--out", str(out), *FAST]) == 0
    err = capsys.readouterr().err
    assert "3 sequences, 11 frames, 0 already done" in err
    names = sorted(p.relative_to(out).as_posix() for p in out.rglob("*.npz"))
    assert names == [f"sequences/{k:02d}/velodyne/{i:06d}.npz" for k in (0, 1) for i in range(4)] + \
        [f"sim/s0/{i:06d}.npz" for i in range(3)]
    plain = tmp_path / "plain"
    assert cli.main(["run", str(kitti_tree / "sequences/01/velodyne"), "--poses",
                     str(kitti_tree / "poses/01.txt"), "--out", str(plain), *FAST]) == 0
    for i in range(4):
        with np.load(out / f"sequences/01/velodyne/{i:06d}.npz") as a, np.load(plain / f"{i:06d}.npz") as b:
            assert np.array_equal(a["mask"], b["mask"])
            np.testing.assert_array_equal(a["flow"], b["flow"])
    capsys.readouterr()
    assert cli.main(["run", str(kitti_tree), "--out", str(out), *FAST]) == 0   # resumed: nothing to do
    assert "11 already done" in capsys.readouterr().err


def test_dataset_user_errors(kitti_tree, tmp_path, capsys):
    out = str(tmp_path / "o")
    assert cli.main(["run", str(kitti_tree), "--out", out, "--poses", "x.txt", *FAST]) == 2
    assert "--poses/--calib name one sequence's files" in capsys.readouterr().err
    assert cli.main(["run", str(kitti_tree), "--out", out, "--max-tasks", "2", *FAST]) == 2
    assert "--max-tasks only applies with --ray" in capsys.readouterr().err
    assert cli.main(["run", str(kitti_tree / "sim/s0"), "--out", out, "--sequences", "a", *FAST]) == 2
    assert "is one sequence" in capsys.readouterr().err
    (kitti_tree / "poses/01.txt").rename(kitti_tree / "poses/01.bak")
    try:
        assert cli.main(["run", str(kitti_tree), "--out", out, *FAST]) == 2
        err = capsys.readouterr().err
        assert "1 of the 3 sequences cannot run" in err and "sequences/01/velodyne: no poses" in err
    finally:
        (kitti_tree / "poses/01.bak").rename(kitti_tree / "poses/01.txt")
