"""``floxels run``'s pipeline: memory stays flat (frames are read a bounded number of frames ahead
of the scan the method asks for, and dropped once behind its window, whatever the chunk size),
and the flow equals the serial path's whatever the chunks."""

import numpy as np
import pytest

from floxels_ext import cli, methods
from floxels_ext.lidar.dataset import layout
from floxels_ext.lidar.pipeline import frame_loader
from floxels_ext.lidar.io.outputs import read_flow_output


def test_frames_held_stay_bounded_over_a_long_chunk(tmp_path, monkeypatch, capsys):
    n = 40
    g = np.random.default_rng(0)
    d = tmp_path / "velodyne"
    d.mkdir()
    for i in range(n):
        xy = g.uniform(-20, 20, (400, 2))
        np.c_[xy, np.full(len(xy), -1.0), np.zeros(len(xy))].astype(np.float32).tofile(d / f"{i:06d}.bin")
    (d / "000017.bin").write_bytes(b"\x00\x01\x02")  # corrupt, mid-chunk: fails alone
    poses = np.tile(np.eye(4)[:3].reshape(1, 12), (n, 1))
    poses[:, 3] = 0.5 * np.arange(n)
    np.savetxt(tmp_path / "poses.txt", poses)

    held = []

    def est(scans, frames, device, options, callback, times=None):
        for f in frames:  # asks for scans in order, like estimate_sequence
            _ = scans[max(0, f - 1):f + 2]
            callback(f, np.zeros((len(scans[f]), 3), np.float32))

    real_prefetch = frame_loader.FrameLoader.prefetch

    def prefetch(self, indices):
        real_prefetch(self, indices)
        held.append(len(self.done) + len(self.futures))

    monkeypatch.setitem(methods._REGISTRY, "fake", methods.Method("fake", "test double", est))
    monkeypatch.setattr(layout, "READ_AHEAD", 4)
    monkeypatch.setattr(layout, "TRANSFORM_AHEAD", 3)
    monkeypatch.setattr(frame_loader.FrameLoader, "prefetch", prefetch)
    rc = cli.main(["run", str(d), "--out", str(tmp_path / "out"), "--method", "fake", "--poses",
                   str(tmp_path / "poses.txt"), "--scans", "3", "--device", "cpu", "--chunk", "64",
                   "--no-ground-removal"])  # flat frames: ground removal would leave nothing (a failed frame)
    err = capsys.readouterr().err
    assert rc == 1 and "000017.bin" in err
    written = sorted(p.name for p in (tmp_path / "out").glob("*.npz"))
    assert len(written) == n - 1 and "000017.npz" not in written
    assert read_flow_output(tmp_path / "out" / "000018.npz")["flow"].shape[1] == 3
    # READ_AHEAD ahead plus the window behind (scans - 1) and the transforms in flight
    assert len(held) > n and max(held) <= 4 + 2 + 3, held


@pytest.mark.parametrize("preset", ["paper", "accurate"])
def test_run_flow_equals_estimate_sequence_on_the_reference_preprocessing(tmp_path, capsys, preset):
    """``floxels run`` (reader threads, the CPU ops, chunked calls, writer threads) gives the flow
    of the serial path: the numpy reference's masks, the scans moved into one world frame,
    ``estimate_sequence``, the flow rotated back into each file's axes; whatever the chunks (each
    chunk's origin is on the 10 m anchor grid, so the method's grids stay aligned). ``accurate``
    (the run's default; the API's is paper) with what the run passes besides the scans: each
    scan's sensor (its pose's translation) and its removed ground returns."""
    from floxels_ext import FloxelsConfig, estimate_sequence
    from floxels_ext.evaluation.sim import simulate_sequence
    from floxels_ext.lidar.dataset.layout import snap_anchor
    from floxels_ext.lidar.preprocess import transform_points
    from floxels_ext.lidar.preprocess.masks import preprocess_classes_numpy
    from floxels_ext.lidar.preprocess.settings import GROUND, KEPT

    seq = simulate_sequence("crossing", 7, 4, beams=16, azimuth_steps=360)
    d = tmp_path / "velodyne"
    d.mkdir()
    raw = []
    for i, fr in enumerate(seq.frames):
        p = transform_points(fr.points, np.linalg.inv(fr.pose))
        raw.append(p)
        np.c_[p, np.zeros(len(p))].astype(np.float32).tofile(d / f"{i:06d}.bin")
    np.savetxt(tmp_path / "poses.txt", np.stack([f.pose[:3] for f in seq.frames]).reshape(-1, 12))
    classes = [preprocess_classes_numpy(p) for p in raw]
    masks = [c == KEPT for c in classes]
    anchor = snap_anchor(seq.frames[0].pose[:3, 3])
    assert np.abs(anchor - seq.frames[0].pose[:3, 3]).max() > 0.1  # the test needs a real snap
    scans, grounds, sensors = [], [], []
    for p, c, fr in zip(raw, classes, seq.frames):
        T = fr.pose.copy()
        T[:3, 3] -= anchor
        scans.append(transform_points(p[c == KEPT], T))
        grounds.append(transform_points(p[c == GROUND], T))
        sensors.append(T[:3, 3])
    # the motion evidence, unexplained groups zeroed (--raw-flow: "score")
    if preset == "paper":
        ref = estimate_sequence(scans, FloxelsConfig(num_scans=3, max_iters=6, evidence="zero"), device="cpu")
    else:
        ref = estimate_sequence(scans, FloxelsConfig.preset("accurate", num_scans=3, max_iters=6), device="cpu",
                                sensor_origins=sensors, ground_points=grounds)
    for chunk in (None, "3", "2"):
        out = tmp_path / f"out{chunk}"
        args = ["run", str(d), "--out", str(out), "--poses", str(tmp_path / "poses.txt"), "--scans", "3",
                "--max-iters", "6", "--device", "cpu", "-q"] + (["--chunk", chunk] if chunk else [])
        assert cli.main(args + (["--preset", "paper"] if preset == "paper" else [])) == 0, capsys.readouterr().err
        for i, fr in enumerate(seq.frames):
            o = read_flow_output(out / f"{i:06d}.npz")
            np.testing.assert_array_equal(o["mask"], masks[i])
            np.testing.assert_allclose(o["flow"][masks[i]], ref[i] @ fr.pose[:3, :3].astype(np.float32),
                                       atol=1e-4, rtol=0)  # float32 rounding of other origins


def test_writers_drain_the_queue_on_more_threads_at_close():
    """What is still queued when the run ends is written on up to ``drain`` threads, all of it."""
    import threading
    import time

    from floxels_ext.lidar.pipeline.stages import Stages
    from floxels_ext.lidar.pipeline.frame_writer import WriterPool

    names, lock = {}, threading.Lock()

    def write_one(i, *rest):
        time.sleep(0.05)
        with lock:
            names[i] = threading.current_thread().name

    pool = WriterPool(write_one, Stages(), workers=1, drain=4)
    for i in range(6):
        pool.put(i, None, None, 0.0, None)
    pool.close()
    assert sorted(names) == list(range(6)) and pool.written == 6
    assert len(set(names.values())) > 1  # the one writer was joined by others


def test_sources_are_absolute_paths_of_the_frame_files(tmp_path, monkeypatch):
    from floxels_ext.lidar.io.sources import discover_input
    from floxels_ext.lidar.io.sources import absolute_sources

    d = tmp_path / "seq"
    d.mkdir()
    for i in range(3):
        np.zeros((10, 4), np.float32).tofile(d / f"{i:06d}.bin")
    monkeypatch.chdir(tmp_path)
    seq = discover_input("seq", bin_columns=4, points_frame="sensor")
    src = absolute_sources(seq, [0, 2])
    assert src == {0: str(d.resolve() / "000000.bin"), 2: str(d.resolve() / "000002.bin")}
