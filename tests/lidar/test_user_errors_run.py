"""``floxels run``: the user errors of issue 17 (each with its exact message or documented result),
the output format (reader, dynamic flag, ego_motion, summary) and the pipeline's plumbing
(timestamps handed to methods, verbosity). A fake method (instant, exact) is used throughout."""

import json
import os

import numpy as np
import pytest

from floxels_ext import cli, methods
from floxels_ext.lidar.io.outputs import read_flow_output
from floxels_ext.lidar.preprocess import transform_points

N = 6
V_WORLD = np.array([0.4, 0.0, 0.0], np.float32)


@pytest.fixture(scope="module")
def seq():
    from floxels_ext.evaluation.sim import simulate_sequence

    return simulate_sequence("crossing", N, 2, beams=16, azimuth_steps=360)


@pytest.fixture
def fake(monkeypatch):
    calls = []

    def est(scans, frames, device, options, callback, times=None):
        calls.append({"n": len(scans), "frames": list(frames), "times": times, "options": dict(options)})
        for f in frames:
            callback(f, np.tile(V_WORLD, (len(scans[f]), 1)))

    monkeypatch.setitem(methods._REGISTRY, "fake", methods.Method("fake", "test double", est))
    return calls


def _bin_dir(seq, d, edit=None):
    d.mkdir(parents=True, exist_ok=True)
    for i, fr in enumerate(seq.frames):
        p = transform_points(fr.points, np.linalg.inv(fr.pose))
        if edit is not None:
            p = edit(i, p)
        np.c_[p, np.zeros(len(p))].astype(np.float32).tofile(d / f"{i:06d}.bin")
    np.savetxt(d.parent / "poses.txt", np.stack([f.pose[:3] for f in seq.frames]).reshape(-1, 12))
    return d


def _run(args, capsys):
    rc = cli.main(["run", *map(str, args), "--device", "cpu"])
    return rc, capsys.readouterr()


def _base(tmp_path, d):
    return [d, "--out", tmp_path / "out", "--method", "fake", "--poses", tmp_path / "poses.txt", "--scans", "3"]


def test_stray_far_rows_do_not_crash(seq, fake, tmp_path, capsys):
    def edit(i, p):
        return np.concatenate([p, [[1e30, 0, 0], [-1e30, 1e30, 1], [1500.0, 0.0, -1.0]]]) if i == 2 else p

    d = _bin_dir(seq, tmp_path / "in", edit)
    rc, cap = _run(_base(tmp_path, d), capsys)
    assert rc == 0, cap.err
    z = read_flow_output(tmp_path / "out" / "000002.npz")
    assert not z["mask"][-3:].any() and np.all(z["flow"][-3:] == 0)


def test_resume_with_other_settings_stops_unless_force(seq, fake, tmp_path, capsys):
    d = _bin_dir(seq, tmp_path / "in")
    assert _run(_base(tmp_path, d), capsys)[0] == 0
    rc, cap = _run(_base(tmp_path, d) + ["--scans", "5"], capsys)
    assert rc == 2 and "was written with other settings" in cap.err and "num_scans: 3 (recorded) vs 5 (now)" in cap.err
    assert "--force" in cap.err
    rc, cap = _run(_base(tmp_path, d) + ["--min-range", "1"], capsys)
    assert rc == 2 and "preprocess" in cap.err
    rc, cap = _run(_base(tmp_path, d) + ["--scans", "5", "--force"], capsys)
    assert rc == 0 and f"{N} frame(s) written" in cap.err
    assert read_flow_output(tmp_path / "out" / "000000.npz", points=False)["num_scans"] == 5
    rc, cap = _run(_base(tmp_path, d) + ["--scans", "5"], capsys)  # same settings: all skipped
    assert rc == 0 and f"{N} already done, 0 to estimate" in cap.err


def test_scans_contradicting_option_is_an_error(seq, fake, tmp_path, capsys):
    d = _bin_dir(seq, tmp_path / "in")
    rc, cap = _run([d, "--out", tmp_path / "out", "--poses", tmp_path / "poses.txt", "--scans", "3",
                    "--option", "num_scans=7"], capsys)
    assert rc == 2 and "--option num_scans=7 contradicts --scans 3" in cap.err


def test_all_nan_frame_fails_alone_and_nan_rows_are_reported(seq, fake, tmp_path, capsys):
    def edit(i, p):
        if i == 3:
            p = np.full_like(p, np.nan)
        if i == 1:
            p = p.copy()
            p[:4] = np.inf
        return p

    d = _bin_dir(seq, tmp_path / "in", edit)
    rc, cap = _run(_base(tmp_path, d), capsys)
    assert rc == 1
    # the reader refuses it (a .bin without one finite row is not a lidar scan), naming the file
    assert "000003.bin" in cap.err and "none of the" in cap.err and "finite coordinates" in cap.err
    assert "1 failed" in cap.err
    assert not (tmp_path / "out" / "000003.npz").exists()
    assert "have rows with NaN/inf coordinates" in cap.err and "000001.bin (4 rows)" in cap.err
    summary = json.loads((tmp_path / "out" / "run_summary.json").read_text())
    assert summary["failed"] == 1 and "000003.bin" in summary["failures"][0]["message"]
    assert summary["nonfinite_rows"] == {"000001": 4}
    assert fake[0]["n"] == N and len(fake) == 1  # the empty scan kept its place (time offsets)


def test_calib_without_poses_and_out_equal_to_input(seq, fake, tmp_path, capsys):
    d = _bin_dir(seq, tmp_path / "in")
    (tmp_path / "calib.txt").write_text("garbage")
    rc, cap = _run([d, "--out", tmp_path / "out", "--no-ego-motion", "--calib", tmp_path / "calib.txt"], capsys)
    assert rc == 2 and "--calib turns the camera poses of --poses into lidar poses; it needs --poses" in cap.err
    rc, cap = _run([d, "--out", d, "--method", "fake", "--poses", tmp_path / "poses.txt"], capsys)
    assert rc == 2 and "is the input directory" in cap.err
    assert sorted(p.suffix for p in d.iterdir()) == [".bin"] * N  # nothing written there
    # --odometry was silently ignored next to --poses
    rc, cap = _run([*_base(tmp_path, d), "--odometry", "kiss-icp"], capsys)
    assert rc == 2 and "--poses FILE and --odometry kiss-icp both give the ego-motion" in cap.err, cap.err
    assert not (tmp_path / "out").exists()


def test_outputs_dynamic_ego_motion_summary_and_reader(seq, fake, tmp_path, capsys):
    d = _bin_dir(seq, tmp_path / "in")
    rc, cap = _run(_base(tmp_path, d) + ["--frames", "1:4", "--dynamic-threshold", "0.3"], capsys)
    assert rc == 0, cap.err
    out = tmp_path / "out"
    for i in (1, 2, 3):
        z = read_flow_output(out / f"{i:06d}.npz")
        with np.load(out / f"{i:06d}.npz") as raw:
            assert "points" not in raw.files  # not repeated by default: read back from 'source'
        np.testing.assert_array_equal(z["points"], np.fromfile(d / f"{i:06d}.bin", np.float32).reshape(-1, 4)[:, :3])
        assert np.array_equal(z["dynamic"], z["mask"])  # |V_WORLD| = 0.4 > 0.3 m per frame
        # ego_motion for every selected frame, the last one (3) included: its next pose is known
        np.testing.assert_allclose(z["ego_motion"], np.linalg.solve(seq.frames[i + 1].pose, seq.frames[i].pose),
                                   atol=1e-9)
        assert z["settings"]["dynamic_threshold"] == 0.3 and z["method"] == "fake"
    summary = json.loads((out / "run_summary.json").read_text())
    assert summary["written"] == 3 and summary["selected"] == 3 and summary["failed"] == 0
    assert set(summary["stages_s"]) >= {"read", "preprocess", "estimate", "write", "outside_estimate"}
    # --self-contained keeps today's files; --compress zips them
    rc, cap = _run(_base(tmp_path, d) + ["--out", tmp_path / "o2", "--self-contained", "--compress",
                                         "--summary", tmp_path / "s.json"], capsys)
    assert rc == 0 and (tmp_path / "s.json").is_file()
    with np.load(tmp_path / "o2" / "000002.npz") as raw:
        assert "points" in raw.files


def test_timestamps_reach_methods_and_quiet_verbosity(seq, fake, tmp_path, capsys):
    pa = pytest.importorskip("pyarrow")
    feather = pytest.importorskip("pyarrow.feather")
    log = tmp_path / "log"
    (log / "sensors" / "lidar").mkdir(parents=True)
    stamps = [1_000_000_000 + 100_000_000 * i + (20_000_000 if i == 4 else 0) for i in range(N)]
    rows = {k: [] for k in ("timestamp_ns", "qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m")}
    for t, fr in zip(stamps, seq.frames):
        p = transform_points(fr.points, np.linalg.inv(fr.pose))
        feather.write_feather(pa.table({"x": p[:, 0], "y": p[:, 1], "z": p[:, 2]}),
                              str(log / "sensors" / "lidar" / f"{t}.feather"))
        yaw = np.arctan2(fr.pose[1, 0], fr.pose[0, 0])
        for k, v in zip(rows, (t, np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2), *fr.pose[:3, 3])):
            rows[k].append(v)
    feather.write_feather(pa.table(rows), str(log / "city_SE3_egovehicle.feather"))
    args = cli.build_parser().parse_args(["run", str(log), "--out", str(tmp_path / "out"), "--method", "fake",
                                          "--device", "cpu", "--scans", "3"])
    args.verbosity = -1
    assert args.func(args) == 0
    # quiet: no header or bar, only the final summary line its help promises (issue 30)
    err = capsys.readouterr().err
    assert err.startswith("done: ") and len(err.strip().splitlines()) == 1, err
    assert np.allclose(fake[0]["times"], [(t - stamps[0]) * 1e-9 for t in stamps])
    z = read_flow_output(tmp_path / "out" / f"{stamps[2]}.npz")
    assert z["timestamp_ns"] == stamps[2]


def test_baseline_method_through_the_pipeline(seq, tmp_path, capsys):
    if "nsfp" not in methods.available_methods():
        pytest.skip("no nsfp baseline")
    d = _bin_dir(seq, tmp_path / "in")
    rc, cap = _run([d, "--out", tmp_path / "out", "--method", "nsfp", "--poses", tmp_path / "poses.txt",
                    "--frames", "2:4", "--option", "max_iters=2"], capsys)
    assert rc == 0, cap.err
    assert sorted(os.listdir(tmp_path / "out")) == ["000002.npz", "000003.npz", "run_summary.json"]
    assert np.isfinite(read_flow_output(tmp_path / "out" / "000002.npz")["flow"]).all()


def test_process_workers_same_outputs_and_clean_interrupt(seq, tmp_path, capsys, monkeypatch):
    """Worker processes give the thread path's files; Ctrl-C leaves no temporaries, no children."""
    import multiprocessing

    done = [0]

    def est(scans, frames, device, options, callback):
        for f in frames:
            if done[0] == options.get("stop_after"):
                raise KeyboardInterrupt
            callback(f, np.tile(V_WORLD, (len(scans[f]), 1)))
            done[0] += 1

    monkeypatch.setitem(methods._REGISTRY, "fake2", methods.Method("fake2", "test double", est))
    d = _bin_dir(seq, tmp_path / "in")
    base = [d, "--method", "fake2", "--poses", tmp_path / "poses.txt", "--scans", "3", "--workers", "2"]
    assert _run(base + ["--out", tmp_path / "t", "--worker-kind", "thread"], capsys)[0] == 0
    assert _run(base + ["--out", tmp_path / "p", "--worker-kind", "process"], capsys)[0] == 0
    for i in range(N):
        a, b = (read_flow_output(tmp_path / k / f"{i:06d}.npz") for k in "tp")
        assert np.array_equal(a["flow"], b["flow"]) and np.array_equal(a["mask"], b["mask"])
    done[0] = 0
    rc, cap = _run(base + ["--out", tmp_path / "i", "--worker-kind", "process", "--option", "stop_after=2"], capsys)
    assert rc == 130
    assert sorted(os.listdir(tmp_path / "i")) == ["000000.npz", "000001.npz"]
    assert multiprocessing.active_children() == []


def test_reader_errors_name_the_file_and_chunk_plan(tmp_path):
    from floxels_ext.lidar.io.outputs import OutputError
    from floxels_ext.lidar.dataset.layout import plan_chunks

    np.savez(tmp_path / "a.npz", flow=np.zeros((3, 3), np.float32))  # no points, no source
    with pytest.raises(OutputError, match="a.npz: no 'points' and no 'source'"):
        read_flow_output(tmp_path / "a.npz")
    assert read_flow_output(tmp_path / "a.npz", points=False)["mask"].all()
    (tmp_path / "b.npz").write_bytes(b"junk")
    with pytest.raises(OutputError, match="b.npz: cannot read"):
        read_flow_output(tmp_path / "b.npz")
    assert [len(c) for c in plan_chunks(list(range(150)), None)] == [128, 22]
    assert [len(c) for c in plan_chunks(list(range(5)), 2)] == [2, 2, 1]


def test_dropped_frames_and_times_txt_reach_methods(seq, fake, tmp_path, capsys):
    """Evenly spaced frames pass no times; a gap in the frame numbers (a dropped scan) and a
    KITTI times.txt do, as offsets the windows follow."""
    d = _bin_dir(seq, tmp_path / "in")
    assert _run(_base(tmp_path, d), capsys)[0] == 0
    assert fake[-1]["times"] is None
    (d / "000003.bin").rename(d / "000009.bin")  # frames 0 1 2 4 5 9: two gaps
    np.savetxt(tmp_path / "poses.txt", np.stack([seq.frames[i].pose[:3] for i in (0, 1, 2, 4, 5, 3)]).reshape(-1, 12))
    rc, cap = _run(_base(tmp_path, d) + ["--force"], capsys)
    assert rc == 0 and "frame times from gaps in the frame numbers" in cap.err
    assert fake[-1]["times"] == [0.0, 1.0, 2.0, 4.0, 5.0, 9.0]
    (d.parent / "times.txt").write_text("\n".join(f"{0.1 * k:.1f}" for k in (0, 1, 2, 3, 5, 6)) + "\n")
    rc, cap = _run(_base(tmp_path, d) + ["--force"], capsys)
    assert rc == 0 and "times.txt" in cap.err
    assert np.allclose(fake[-1]["times"], [0.0, 0.1, 0.2, 0.3, 0.5, 0.6])
    (d.parent / "times.txt").write_text("0.0\n0.1\n")
    rc, cap = _run(_base(tmp_path, d) + ["--force"], capsys)
    assert rc == 0 and "holds 2 values for 6 frames" in cap.err and fake[-1]["times"] is None
