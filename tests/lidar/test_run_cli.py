"""``floxels run`` / ``accumulate`` / ``show`` end to end on a tiny simulated sequence written in
several lidar formats. Most tests use a fake method (exact, instant) registered for the test, so
they check the plumbing (formats, ego-motion, point order, masks, resumability, errors) exactly;
one test runs the real Floxels estimator for a few iterations."""

import os

import numpy as np
import pytest

from floxels_ext import cli, methods
from floxels_ext.lidar.io.writers import write_ply
from floxels_ext.lidar.io.outputs import read_flow_output
from floxels_ext.lidar.preprocess import transform_points
from floxels_ext.evaluation.seqio import save_sequence

N_FRAMES = 5
V_WORLD = np.array([0.3, -0.2, 0.05], np.float32)  # what the fake method answers, in world axes


@pytest.fixture(scope="module")
def seq():
    from floxels_ext.evaluation.sim import simulate_sequence

    return simulate_sequence("crossing", N_FRAMES, 0, beams=16, azimuth_steps=360)


@pytest.fixture
def fake(monkeypatch):
    """A method answering V_WORLD for every point, recording what it was given."""
    calls, done = [], [0]

    def est(scans, frames, device, options, callback):
        calls.append(([np.array(s) for s in scans], list(frames), dict(options)))
        for f in frames:
            if done[0] == options.get("interrupt_after"):
                raise KeyboardInterrupt
            callback(f, np.tile(V_WORLD, (len(scans[f]), 1)))
            done[0] += 1

    monkeypatch.setitem(methods._REGISTRY, "fake", methods.Method("fake", "test double", est))
    return calls


def _sensor_points(fr):
    return transform_points(fr.points, np.linalg.inv(fr.pose))


def _write(seq, d, fmt):
    """Frames in their sensor frames (+ poses file) in format ``fmt``; returns the INPUT dir."""
    d.mkdir(parents=True, exist_ok=True)
    for i, fr in enumerate(seq.frames):
        p = _sensor_points(fr)
        if i == 1:
            p[7] = np.nan  # a NaN row must keep its place
        if fmt == "bin":
            np.c_[p, np.zeros(len(p))].astype(np.float32).tofile(d / f"{i:06d}.bin")
        elif fmt == "npy":
            np.save(d / f"scan_{i}.npy", p)
        elif fmt == "npz":  # per-frame pose inside the file: no poses file needed
            np.savez(d / f"f{i}.npz", points=p, pose=fr.pose)
        elif fmt == "ply":
            write_ply(d / f"{i}.ply", p)
        elif fmt == "pcd":
            hdr = (f"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {len(p)}\nHEIGHT 1\n"
                   f"POINTS {len(p)}\nDATA binary\n").encode()
            (d / f"{i}.pcd").write_bytes(hdr + p.astype("<f4").tobytes())
    if fmt != "npz":
        np.savetxt(d.parent / f"{d.name}_poses.txt", np.stack([f.pose[:3] for f in seq.frames]).reshape(-1, 12))
    return d


def _listing(d):
    """The files of an OUT_DIR but the run summary (temporaries included: none may remain)."""
    return sorted(f for f in os.listdir(d) if f != "run_summary.json")


def _run(args, capsys=None):
    rc = cli.main(["run", *map(str, args), "--device", "cpu"])
    out = capsys.readouterr() if capsys is not None else None
    return rc, out


def _check_outputs(seq, out, names, nan_frame=1):
    for i, name in enumerate(names):
        z = read_flow_output(out / f"{name}.npz")
        flow, mask, pts = z["flow"], z["mask"], z["points"]
        assert z["method"] == "fake"
        n = len(seq.frames[i])
        assert flow.shape == (n, 3) and mask.shape == (n,) and pts.shape == (n, 3)
        finite = np.isfinite(pts).all(1)
        assert 0 < mask.sum() < finite.sum()  # cropping + ground removal dropped some
        assert not mask[~finite].any()
        if i == nan_frame:
            assert not finite[7] and np.isnan(flow[7]).all()
        # the world-axes answer, rotated into the frame's own coordinates; 0 where not optimised
        R = seq.frames[i].pose[:3, :3]
        np.testing.assert_allclose(flow[mask], np.tile(V_WORLD @ R, (mask.sum(), 1)), atol=1e-5)
        assert np.all(flow[finite & ~mask] == 0)


@pytest.mark.parametrize("fmt", ["bin", "pcd", "ply", "npy", "npz"])
def test_run_formats_with_poses(seq, fake, tmp_path, fmt, capsys):
    d = _write(seq, tmp_path / "in", fmt)
    args = [d, "--out", tmp_path / "out", "--method", "fake", "--scans", "3"]
    if fmt != "npz":
        args += ["--poses", tmp_path / "in_poses.txt"]
    rc, cap = _run(args, capsys)
    assert rc == 0, cap.err
    names = sorted((p.stem for p in (tmp_path / "out").glob("*.npz")), key=lambda s: int("".join(filter(str.isdigit, s))))
    assert len(names) == N_FRAMES
    _check_outputs(seq, tmp_path / "out", names)
    assert "5 frame(s) written" in cap.err and "s/frame mean" in cap.err
    # ego-motion compensation: the scans handed to the method share one frame, so static
    # structure (a building wall) lines up: nearest-neighbour distances between consecutive scans are small
    from scipy.spatial import cKDTree

    scans = fake[0][0]
    d01 = cKDTree(scans[0]).query(scans[1])[0]
    assert np.median(d01) < 0.3


def test_run_seqio_and_av2(seq, fake, tmp_path, capsys):
    save_sequence(tmp_path / "sim", seq)
    rc, cap = _run([tmp_path / "sim", "--out", tmp_path / "o1", "--method", "fake"], capsys)
    assert rc == 0, cap.err
    z = read_flow_output(tmp_path / "o1" / "000002.npz")  # seqio points are in the world frame already
    np.testing.assert_allclose(z["flow"][z["mask"]], np.tile(V_WORLD, (z["mask"].sum(), 1)), atol=1e-6)
    np.testing.assert_array_equal(z["points"], seq.frames[2].points)
    # Argoverse 2 log layout
    pa = pytest.importorskip("pyarrow")
    feather = pytest.importorskip("pyarrow.feather")
    from floxels_ext.lidar.io.poses import quat_to_matrix  # noqa: F401

    log = tmp_path / "av2log"
    (log / "sensors" / "lidar").mkdir(parents=True)
    stamps = [315966265659927216 + 100_000_000 * i for i in range(N_FRAMES)]
    rows = {k: [] for k in ("timestamp_ns", "qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m")}
    for t, fr in zip(stamps, seq.frames):
        p = _sensor_points(fr)
        feather.write_feather(pa.table({"x": p[:, 0], "y": p[:, 1], "z": p[:, 2]}),
                              str(log / "sensors" / "lidar" / f"{t}.feather"))
        R = fr.pose[:3, :3]
        yaw = np.arctan2(R[1, 0], R[0, 0])  # the simulated ego only yaws
        for k, v in zip(rows, (t, np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2), *fr.pose[:3, 3])):
            rows[k].append(v)
    feather.write_feather(pa.table(rows), str(log / "city_SE3_egovehicle.feather"))
    rc, cap = _run([log, "--out", tmp_path / "o2", "--method", "fake"], capsys)
    assert rc == 0, cap.err
    _check_outputs(seq, tmp_path / "o2", [str(t) for t in stamps], nan_frame=None)


def test_resume_skips_and_cleans_temp_files(seq, fake, tmp_path, capsys):
    d = _write(seq, tmp_path / "in", "bin")
    args = [d, "--out", tmp_path / "out", "--method", "fake", "--poses", tmp_path / "in_poses.txt"]
    assert _run(args, capsys)[0] == 0
    stamp = os.stat(tmp_path / "out" / "000000.npz").st_mtime_ns
    # an interrupted write leaves a temporary file; a frame output is missing
    (tmp_path / "out" / "000003.npz").unlink()
    (tmp_path / "out" / ".000003.npz.99999.tmp").write_bytes(b"half")
    rc, cap = _run(args, capsys)
    assert rc == 0
    assert "4 already done, 1 to estimate" in cap.err and "removed 1 temporary" in cap.err
    assert _listing(tmp_path / "out") == [f"{i:06d}.npz" for i in range(N_FRAMES)]
    assert os.stat(tmp_path / "out" / "000000.npz").st_mtime_ns == stamp
    assert len(fake[-1][1]) == 1  # only the missing frame was estimated
    rc, cap = _run(args + ["--force", "--frames", "1:3"], capsys)
    assert rc == 0 and "2 frame(s) written" in cap.err


def test_resume_with_the_poses_file_named_another_way(seq, fake, tmp_path, capsys, monkeypatch):
    d = _write(seq, tmp_path / "in", "bin")
    assert _run([d, "--out", tmp_path / "out", "--method", "fake", "--poses", tmp_path / "in_poses.txt",
                 "--frames", "0:3"], capsys)[0] == 0
    monkeypatch.chdir(tmp_path)  # the same poses file, now by a relative path
    rc, cap = _run(["in", "--out", "out", "--method", "fake", "--poses", "in_poses.txt"], capsys)
    assert rc == 0, cap.err
    assert "3 already done, 2 to estimate" in cap.err


def test_interrupt_leaves_only_complete_files(seq, fake, tmp_path, capsys):
    d = _write(seq, tmp_path / "in", "bin")
    rc, cap = _run([d, "--out", tmp_path / "out", "--method", "fake", "--poses", tmp_path / "in_poses.txt",
                    "--option", "interrupt_after=2"], capsys)
    assert rc == 130
    files = _listing(tmp_path / "out")
    assert files == ["000000.npz", "000001.npz"]  # complete frames only, no temporaries
    for f in files:
        with np.load(tmp_path / "out" / f) as z:
            assert z["flow"].shape[1] == 3


def test_corrupt_and_empty_frames_do_not_stop_the_others(seq, fake, tmp_path, capsys):
    d = _write(seq, tmp_path / "in", "bin")
    (d / "000002.bin").write_bytes(b"\0" * 7)       # truncated
    (d / "000003.bin").write_bytes(b"")             # no points
    rc, cap = _run([d, "--out", tmp_path / "out", "--method", "fake", "--poses", tmp_path / "in_poses.txt"], capsys)
    assert rc == 1
    assert "000002.bin" in cap.err and "truncated" in cap.err
    assert "000003.bin" in cap.err and "no points" in cap.err
    assert "2 failed" in cap.err
    assert _listing(tmp_path / "out") == ["000000.npz", "000001.npz", "000004.npz"]
    scans = fake[0][0]
    assert len(scans) == N_FRAMES and len(scans[2]) == 0 and len(scans[3]) == 0  # time offsets kept


def test_user_errors_exit_2(seq, fake, tmp_path, capsys):
    d = _write(seq, tmp_path / "in", "bin")
    out = ["--out", tmp_path / "out"]
    rc, cap = _run([d, *out, "--method", "fake"], capsys)
    assert rc == 2 and "no poses" in cap.err and "--odometry kiss-icp" in cap.err and "--no-ego-motion" in cap.err
    np.save(tmp_path / "p3.npy", np.stack([np.eye(4)] * 3))
    rc, cap = _run([d, *out, "--method", "fake", "--poses", tmp_path / "p3.npy"], capsys)
    assert rc == 2 and "p3.npy: 3 poses" in cap.err and "5 frames" in cap.err
    np.save(tmp_path / "bad.npy", np.zeros((5, 2, 2)))
    rc, cap = _run([d, *out, "--method", "fake", "--poses", tmp_path / "bad.npy"], capsys)
    assert rc == 2 and "bad.npy" in cap.err and "shape" in cap.err
    rc, cap = _run([d, *out, "--method", "nope", "--no-ego-motion"], capsys)
    assert rc == 2 and "unknown --method" in cap.err
    rc, cap = _run([d, *out, "--option", "voxel_sise=0.3", "--no-ego-motion"], capsys)
    assert rc == 2 and "voxel_sise" in cap.err
    rc, cap = _run([tmp_path / "missing", *out, "--no-ego-motion"], capsys)
    assert rc == 2 and "does not exist" in cap.err
    (tmp_path / "mixed").mkdir()
    (tmp_path / "mixed" / "a.bin").write_bytes(b"")
    (tmp_path / "mixed" / "b.ply").write_bytes(b"")
    rc, cap = _run([tmp_path / "mixed", *out, "--no-ego-motion"], capsys)
    assert rc == 2 and "several formats" in cap.err and "--ext" in cap.err
    rc, cap = _run([d, *out, "--method", "fake", "--no-ego-motion", "--frames", "9:"], capsys)
    assert rc == 2 and "selects no frame" in cap.err
    rc, cap = _run([d, *out, "--method", "fake", "--odometry", "kiss-icp", "--no-ego-motion"], capsys)
    assert rc == 2 and "contradicts" in cap.err
    save_sequence(tmp_path / "sim", seq)
    rc, cap = _run([tmp_path / "sim", *out, "--method", "fake", "--poses", tmp_path / "in_poses.txt"], capsys)
    assert rc == 2 and "already in one world frame" in cap.err


def test_odometry_missing_is_a_clear_error(seq, fake, tmp_path, capsys, monkeypatch):
    import importlib

    real = importlib.import_module
    monkeypatch.setattr(importlib, "import_module",
                        lambda n, *a: (_ for _ in ()).throw(ImportError(n)) if n.startswith("kiss_icp") else real(n, *a))
    d = _write(seq, tmp_path / "in", "bin")
    rc, cap = _run([d, "--out", tmp_path / "out", "--method", "fake", "--odometry", "kiss-icp"], capsys)
    assert rc == 2 and "pip install 'floxels_ext[odometry]'" in cap.err


def test_floxels_end_to_end_then_eval_show_accumulate(seq, tmp_path, capsys):
    save_sequence(tmp_path / "sim", seq)
    out = tmp_path / "out"
    rc, cap = _run([tmp_path / "sim", "--out", out, "--scans", "3", "--max-iters", "8"], capsys)
    assert rc == 0, cap.err
    assert _listing(out) == [f"{i:06d}.npz" for i in range(N_FRAMES)]
    assert cli.main(["eval", str(out), str(tmp_path / "sim")]) == 0  # same names, same point order
    with np.load(out / "000002.npz") as z:
        assert z["flow"].dtype == np.float32 and np.isfinite(z["flow"]).all() and str(z["method"]) == "floxels"
    png = tmp_path / "f.png"
    assert cli.main(["show", str(out), "--frame", "000002", "--png", str(png), "--extent", "20"]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    ply = tmp_path / "acc.ply"
    assert cli.main(["accumulate", str(out), "000002", "--out", str(ply), "--neighbours", "1"]) == 0
    from floxels_ext.lidar.io import read_points

    acc = read_points(ply)
    assert len(acc) == sum(len(seq.frames[i]) for i in (1, 2, 3))
    assert set(np.unique(acc.fields["time_offset"]).tolist()) == {-1, 0, 1}
    capsys.readouterr()
    assert cli.main(["show", str(tmp_path / "nothing")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_show_rerun_missing_and_fake(tmp_path, capsys, monkeypatch):
    import sys
    import types

    pts = np.random.default_rng(0).normal(scale=5, size=(50, 3)).astype(np.float32)
    flow = np.zeros_like(pts)
    flow[:10] = [1.0, 0, 0]
    np.savez(tmp_path / "f.npz", points=pts, flow=flow, mask=np.ones(50, bool))
    monkeypatch.setitem(sys.modules, "rerun", None)  # import rerun -> ImportError
    rc = cli.main(["show", str(tmp_path / "f.npz"), "--png", str(tmp_path / "a.png"), "--rerun", str(tmp_path / "r.rrd")])
    assert rc == 2 and "pip install 'floxels_ext[viz]'" in capsys.readouterr().err
    assert not (tmp_path / "a.png").exists()  # refused before any work (the PNG was written first)
    rc = cli.main(["show", str(tmp_path / "f.npz"), "--png", str(tmp_path / "a.png"), "--rerun", str(tmp_path)])
    assert rc == 2 and f"--rerun {tmp_path} is an existing directory" in capsys.readouterr().err
    logged = {}
    rr = types.SimpleNamespace(init=lambda *a, **k: None, save=lambda p: logged.setdefault("save", p),
                               log=lambda path, obj: logged.setdefault(path, obj),
                               Points3D=lambda pts, **k: ("points", len(pts)),
                               Arrows3D=lambda origins, vectors, **k: ("arrows", len(vectors)))
    monkeypatch.setitem(sys.modules, "rerun", rr)
    rc = cli.main(["show", str(tmp_path / "f.npz"), "--png", str(tmp_path / "a.png"), "--rerun", str(tmp_path / "r.rrd")])
    assert rc == 0
    assert logged["f/points"] == ("points", 50) and logged["f/flow"] == ("arrows", 10)


@pytest.mark.parametrize("module", ["floxels_ext", "floxels_ext.cli"])
def test_python_dash_m_reports_user_errors_without_traceback(tmp_path, module):
    """``python -m floxels_ext[.cli]`` is the ``floxels`` command (the CLI's errors are one
    class however the module is started)."""
    import subprocess
    import sys

    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
    r = subprocess.run([sys.executable, "-m", module, "run", str(tmp_path / "missing"), "--out", str(tmp_path / "o")],
                       capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 2, r.stderr
    assert r.stderr.startswith("floxels: error:") and "Traceback" not in r.stderr


def test_motion_evidence_fields_switch_and_resume(seq, tmp_path, capsys):
    """floxels run writes the motion evidence into every frame and zeroes unexplained groups by
    default; --raw-flow keeps the paper's flow; the setting is compared on resume."""
    save_sequence(tmp_path / "sim", seq)
    out, raw = tmp_path / "out", tmp_path / "raw"
    args = [tmp_path / "sim", "--scans", "3", "--max-iters", "8", "--frames", "1:3"]
    rc, cap = _run([*args, "--out", out], capsys)
    assert rc == 0, cap.err
    rc, cap = _run([*args, "--out", raw, "--raw-flow"], capsys)
    assert rc == 0, cap.err
    for name in ("000001", "000002"):
        z, r = read_flow_output(out / f"{name}.npz"), read_flow_output(raw / f"{name}.npz")
        assert z["settings"]["options"]["evidence"] == "zero" and r["settings"]["options"]["evidence"] == "score"
        for d in (z, r):
            ev, ex, mask = d["evidence"], d["explained"], d["mask"]
            assert ev.dtype == np.float32 and ex.dtype == bool and ev.shape == ex.shape == mask.shape
            assert np.isfinite(ev[mask]).all() and np.isnan(ev[~mask]).all() and not ex[~mask].any()
        np.testing.assert_array_equal(z["explained"], r["explained"])
        np.testing.assert_array_equal(z["evidence"], r["evidence"])
        # default: the raw flow where explained, 0 elsewhere; dynamic follows the written flow
        np.testing.assert_array_equal(z["flow"], np.where(r["explained"][:, None], r["flow"], 0))
        assert not (z["dynamic"] & ~z["explained"]).any()
        # explained is the final verdict: a group whose flow the evidence zeroed is not explained
        assert (np.abs(z["flow"][z["explained"]]).sum(axis=1) > 0).all()
    # resume with the other setting: stopped (an output of other settings), --force recomputes
    rc, cap = _run([*args, "--out", out, "--raw-flow"], capsys)
    assert rc == 2 and "evidence" in cap.err
    rc, cap = _run([*args, "--out", raw, "--raw-flow", "--option", "evidence=zero"], capsys)
    assert rc == 2 and "--raw-flow contradicts" in cap.err
    rc, cap = _run([*args, "--out", out], capsys)
    assert rc == 0 and "2 already done" in cap.err


def test_default_preset_is_accurate_and_paper_outputs_say_how_to_resume(seq, tmp_path, capsys):
    """floxels run's default is accurate (issue 42); a run resumed over outputs of the paper
    preset (earlier versions' default) stops and says how to continue them."""
    save_sequence(tmp_path / "sim", seq)
    args = [tmp_path / "sim", "--out", tmp_path / "o", "--max-iters", "2", "--frames", "2:3"]
    rc, cap = _run([*args, "--preset", "paper"], capsys)
    assert rc == 0, cap.err
    assert read_flow_output(tmp_path / "o" / "000002.npz")["settings"]["num_scans"] == 5
    rc, cap = _run(args, capsys)
    assert rc == 2 and "--preset paper continues outputs of the paper's settings" in cap.err
    rc, cap = _run([*args, "--force"], capsys)
    assert rc == 0, cap.err
    d = read_flow_output(tmp_path / "o" / "000002.npz")
    assert d["settings"]["num_scans"] == 11 and d["settings"]["options"]["visibility"] is True


def test_preset_accurate(seq, tmp_path, capsys, fake):
    """--preset accurate: the preset's fields are the run's options, its 11-scan window unless
    --scans is given; with another method it is a user error."""
    save_sequence(tmp_path / "sim", seq)
    args = [tmp_path / "sim", "--max-iters", "3", "--frames", "2:3", "--preset", "accurate"]
    rc, cap = _run([*args, "--out", tmp_path / "acc"], capsys)
    assert rc == 0, cap.err
    d = read_flow_output(tmp_path / "acc" / "000002.npz")
    assert d["settings"]["num_scans"] == 11
    opts = d["settings"]["options"]
    assert opts["rigid_refine"] is True and opts["refine_max_supports"] == 2 and opts["evidence"] == "zero" and "velocity_search" not in opts
    rc, cap = _run([*args, "--out", tmp_path / "acc3", "--scans", "3"], capsys)
    assert rc == 0, cap.err
    assert read_flow_output(tmp_path / "acc3" / "000002.npz")["settings"]["num_scans"] == 3
    rc, cap = _run([*args, "--out", tmp_path / "f", "--method", "fake"], capsys)
    assert rc == 2 and "--preset accurate sets Floxels options" in cap.err
    rc, cap = _run([tmp_path / "sim", "--out", tmp_path / "p", "--preset", "fast"], capsys)
    assert rc == 2 and "fast" in cap.err


def test_a_slice_from_the_end_needs_no_equals_sign():
    # argparse read "-1:" as the next option ("expected one argument"); only --frames=-1: worked
    from floxels_ext.cli import _slice_values, build_parser

    for given in ("-1:", "-3:-1", "-2:"):
        args = build_parser().parse_args(_slice_values(["run", "x", "--out", "o", "--frames", given]))
        assert args.frames == given
    assert _slice_values(["run", "x", "--frames", "-q"]) == ["run", "x", "--frames", "-q"]  # an option stays one
    assert _slice_values(["eval", "p", "g", "--frames", "-2:"]) == ["eval", "p", "g", "--frames=-2:"]
