"""Every branch of ``floxels run``'s resume, through the CLI entry point (issue 34, issue 30 item 4):
missing, unreadable and truncated outputs, temporaries of an interrupted write, settings or
method changed (refused without --force), and inputs changed since a frame was written (a fixed
failed frame, an edited scan, a poses file edited in place, times.txt changed or removed, a
frame added): exactly the frames whose window used a changed input are recomputed, and the
result equals a fresh run. Outputs of earlier versions (no input record) are kept, with a warning.

The method is a test double whose answer depends on its window (the number of empty scans
next to the frame), so an output computed with a broken neighbour differs from a fresh one.
"""

import os

import numpy as np
import pytest

from floxels_ext import cli, methods
from floxels_ext.lidar.io.outputs import read_flow_output, write_output
from floxels_ext.lidar.preprocess import transform_points

N_FRAMES = 7
V_WORLD = np.array([0.3, -0.2, 0.05], np.float32)


def _drop_last_point(f) -> None:
    """Rewrite the simulated frame file ``f`` with its last point (and the rows of its per-point
    arrays) removed."""
    with np.load(f) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["points"] = arrays["points"][:-1]
    for k in ("flow", "dynamic", "labels", "ground"):
        if k in arrays and len(arrays[k]) == len(arrays["points"]) + 1:
            arrays[k] = arrays[k][:-1]
    np.savez(f, **arrays)


@pytest.fixture(scope="module")
def seq():
    from floxels_ext.evaluation.sim import simulate_sequence

    return simulate_sequence("crossing", N_FRAMES, 0, beams=8, azimuth_steps=180)


@pytest.fixture
def fake(monkeypatch):
    """Answers V_WORLD * (1 + empty scans among the frame's neighbours); records the frames."""
    estimated = []

    def est(scans, frames, device, options, callback):
        for f in frames:
            empty = sum(1 for j in (f - 1, f + 1) if 0 <= j < len(scans) and len(scans[j]) == 0)
            estimated.append(f)
            callback(f, np.tile(V_WORLD * (1 + empty), (len(scans[f]), 1)))

    monkeypatch.setitem(methods._REGISTRY, "fake", methods.Method("fake", "test double", est))
    monkeypatch.setitem(methods._REGISTRY, "fake2", methods.Method("fake2", "another test double", est))
    return estimated


def _write_input(seq, d):
    d.mkdir(parents=True, exist_ok=True)
    for i, fr in enumerate(seq.frames):
        p = transform_points(fr.points, np.linalg.inv(fr.pose))
        np.c_[p, np.zeros(len(p))].astype(np.float32).tofile(d / f"{i:06d}.bin")
    np.savetxt(d.parent / "poses.txt", np.stack([f.pose[:3] for f in seq.frames]).reshape(-1, 12))
    return d


def _run(capsys, d, out, *extra):
    rc = cli.main(["run", str(d), "--out", str(out), "--method", "fake", "--poses", str(d.parent / "poses.txt"),
                   "--scans", "3", "--device", "cpu", *map(str, extra)])
    return rc, capsys.readouterr().err


def _names(frames):
    return sorted(f"{i:06d}" for i in frames)


def _snapshot(out):
    """Each output's (inode, mtime): a rewrite (atomic rename) changes both."""
    return {p.stem: (p.stat().st_ino, p.stat().st_mtime_ns) for p in out.glob("*.npz")}


def _rewritten(before, out):
    now = _snapshot(out)
    return sorted(k for k in now if before.get(k) != now[k])


def _flows(out):
    return {p.stem: read_flow_output(p)["flow"] for p in sorted(out.glob("*.npz"))}


def _fresh(capsys, d, tmp_path):
    out = tmp_path / "fresh"
    rc, err = _run(capsys, d, out)
    assert rc == 0, err
    return _flows(out)


@pytest.fixture
def done(seq, fake, tmp_path, capsys):
    """A complete run: (input dir, out dir)."""
    d = _write_input(seq, tmp_path / "in")
    out = tmp_path / "out"
    rc, err = _run(capsys, d, out)
    assert rc == 0, err
    assert len(fake) == N_FRAMES
    return d, out


def test_nothing_changed_nothing_recomputed(done, fake, capsys):
    d, out = done
    n = len(fake)
    snap = _snapshot(out)
    rc, err = _run(capsys, d, out)
    assert rc == 0 and f"{N_FRAMES} already done, 0 to estimate" in err
    assert fake[n:] == []
    for p in out.glob("*.npz"):  # the record of what each output was computed from
        with np.load(p) as z:
            assert "inputs" in z.files


@pytest.mark.parametrize("damage", ["garbage", "truncated", "empty", "not_an_output"])
def test_unreadable_output_is_recomputed(done, fake, capsys, damage):
    d, out = done
    p = out / "000004.npz"
    good = p.read_bytes()
    if damage == "garbage":
        p.write_bytes(b"\x00" * 100)
    elif damage == "truncated":  # a crash after the rename, before the data reached the disk
        p.write_bytes(good[: len(good) // 2])
    elif damage == "empty":
        p.write_bytes(b"")
    else:
        np.savez(p, something=np.zeros(3))
    n = len(fake)
    snap = _snapshot(out)
    rc, err = _run(capsys, d, out)
    assert rc == 0, err
    assert "6 already done, 1 to estimate" in err and "cannot be read" in err and "000004.npz" in err
    assert _rewritten(snap, out) == ["000004"]
    assert p.read_bytes() != b"" and read_flow_output(p)["flow"].shape[1] == 3


def test_half_written_temporaries_are_removed_and_their_frames_written(done, fake, capsys):
    d, out = done
    (out / "000002.npz").unlink()
    # an interrupted write: the temporary of a selected frame (even one that looks complete) and
    # one of a frame outside --frames, which another run (a Ray task) may be writing
    (out / ".000002.npz.4242.tmp").write_bytes((out / "000003.npz").read_bytes())
    (out / ".000006.npz.4242.tmp").write_bytes(b"half")
    n = len(fake)
    snap = _snapshot(out)
    rc, err = _run(capsys, d, out, "--frames", "0:5")
    assert rc == 0, err
    assert "removed 1 temporary" in err and "4 already done, 1 to estimate" in err
    assert _rewritten(snap, out) == ["000002"]
    assert not (out / ".000002.npz.4242.tmp").exists() and (out / ".000006.npz.4242.tmp").exists()


@pytest.mark.parametrize("change,what", [(["--max-range", "40"], "preprocess"),
                                         (["--option", "speed=2"], "options"),
                                         (["--dynamic-threshold", "0.1"], "dynamic_threshold"),
                                         (["--scans", "5"], "num_scans")])
def test_settings_changed_stop_the_run_unless_force(done, fake, capsys, change, what):
    d, out = done
    before = {p.name: p.stat().st_mtime_ns for p in out.glob("*.npz")}
    n = len(fake)
    snap = _snapshot(out)
    rc, err = _run(capsys, d, out, *change)
    assert rc == 2 and "written with other settings" in err and what in err and "--force" in err
    assert fake[n:] == [] and {p.name: p.stat().st_mtime_ns for p in out.glob("*.npz")} == before
    rc, err = _run(capsys, d, out, *change, "--force")
    assert rc == 0 and f"{N_FRAMES} frame(s) written" in err


def test_method_changed_stops_the_run(done, fake, capsys):
    d, out = done
    rc = cli.main(["run", str(d), "--out", str(out), "--method", "fake2", "--poses", str(d.parent / "poses.txt"),
                   "--scans", "3", "--device", "cpu"])
    err = capsys.readouterr().err
    assert rc == 2 and "method: 'fake' (recorded) vs 'fake2' (now)" in err


def test_fixed_failed_frame_recomputes_its_neighbours(seq, fake, tmp_path, capsys):
    d = _write_input(seq, tmp_path / "in")
    good = (d / "000003.bin").read_bytes()
    (d / "000003.bin").write_bytes(b"\0" * 7)  # truncated: frame 3 fails, 2 and 4 see an empty scan
    out = tmp_path / "out"
    rc, err = _run(capsys, d, out)
    assert rc == 1 and "000003.bin" in err
    (d / "000003.bin").write_bytes(good)  # the user fixes it
    n = len(fake)
    snap = _snapshot(out)
    rc, err = _run(capsys, d, out)
    assert rc == 0, err
    # frame 3 (missing) and the frames whose windows (3 scans) hold frame 3: 2 and 4
    assert _rewritten(snap, out) == ["000002", "000003", "000004"]
    assert "recomputing 2 frame(s) whose inputs changed" in err and "000003 changed" in err
    fresh = _fresh(capsys, d, tmp_path)
    got = _flows(out)
    assert got.keys() == fresh.keys()
    for k in fresh:
        np.testing.assert_array_equal(got[k], fresh[k], err_msg=k)


def test_edited_scan_recomputes_the_windows_that_hold_it(done, fake, capsys):
    d, out = done
    p = d / "000005.bin"
    a = np.fromfile(p, np.float32).reshape(-1, 4)
    a[:10, 0] += 0.5
    a.tofile(p)
    st = p.stat()
    os.utime(p, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))  # same size: the time tells
    n = len(fake)
    snap = _snapshot(out)
    rc, err = _run(capsys, d, out)
    assert rc == 0, err
    assert _rewritten(snap, out) == ["000004", "000005", "000006"]


def test_poses_file_edited_in_place(done, fake, capsys, seq):
    d, out = done
    poses = np.stack([f.pose[:3] for f in seq.frames]).reshape(-1, 12)
    poses[1, 3] += 0.25  # frame 1's position; same file, same path
    np.savetxt(d.parent / "poses.txt", poses)
    n = len(fake)
    snap = _snapshot(out)
    rc, err = _run(capsys, d, out)
    assert rc == 0, err
    # windows holding frame 1 (3 scans, shifted inwards at the start): 0, 1, 2
    assert _rewritten(snap, out) == ["000000", "000001", "000002"]
    assert "poses" in err


def test_times_file_changed_or_removed(done, fake, capsys):
    d, out = done
    times = d / "times.txt"
    t = np.arange(N_FRAMES) * 0.1
    np.savetxt(times, t)  # times appear: every frame's offsets are now given
    n = len(fake)
    snap = _snapshot(out)
    rc, err = _run(capsys, d, out)
    assert rc == 0, err
    assert _rewritten(snap, out) == _names(range(N_FRAMES)) and "frame times now given" in err
    t[5] += 0.05  # a late scan: the windows holding frame 5
    np.savetxt(times, t)
    n = len(fake)
    snap = _snapshot(out)
    rc, err = _run(capsys, d, out)
    assert rc == 0, err
    assert _rewritten(snap, out) == ["000004", "000005", "000006"]
    times.unlink()
    n = len(fake)
    snap = _snapshot(out)
    rc, err = _run(capsys, d, out)
    assert rc == 0, err
    assert _rewritten(snap, out) == _names(range(N_FRAMES)) and "no longer given" in err


def test_frame_added_at_the_end(done, fake, capsys, seq):
    d, out = done
    (d / f"{N_FRAMES:06d}.bin").write_bytes((d / f"{N_FRAMES - 1:06d}.bin").read_bytes())
    poses = np.stack([f.pose[:3] for f in seq.frames] + [seq.frames[-1].pose[:3]]).reshape(-1, 12)
    np.savetxt(d.parent / "poses.txt", poses)
    n = len(fake)
    snap = _snapshot(out)
    rc, err = _run(capsys, d, out)
    assert rc == 0, err
    # the new frame, and the last one, whose window [4, 7) moved to [5, 8) and now has a next scan
    assert _rewritten(snap, out) == ["000006", "000007"]


def test_outputs_of_earlier_versions_are_kept_with_a_warning(done, fake, capsys):
    d, out = done
    for p in sorted(out.glob("*.npz"))[:2]:  # as an earlier version wrote them: no 'inputs'
        with np.load(p) as z:
            arrays = {k: z[k] for k in z.files if k != "inputs"}
        write_output(p, **arrays)
    (d / "000000.bin").write_bytes((d / "000000.bin").read_bytes()[:-16])  # one point fewer
    n = len(fake)
    snap = _snapshot(out)
    rc, err = _run(capsys, d, out)
    assert rc == 0, err
    # frame 2's window [1, 4) does not hold frame 0; frames 0 and 1 have no record: kept
    assert fake[n:] == []
    assert "2 output(s) were written by an earlier version" in err and "--force" in err


def test_dataset_sequence_recomputes_changed_inputs(tmp_path, capsys):
    """A dataset's sequences are checked as ``floxels run`` checks one (lidar/dataset/sequence.py),
    for every sequence that has work left; the other sequence is not touched."""
    from floxels_ext.evaluation.seqio import save_sequence
    from floxels_ext.evaluation.sim import simulate_sequence

    root, out = tmp_path / "data", tmp_path / "out"
    for k in range(2):
        save_sequence(root / f"s{k}", simulate_sequence("crossing", 7 - 2 * k, k, beams=8, azimuth_steps=180))
    argv = ["run", str(root), "--out", str(out), "--device", "cpu", "--scans", "3", "--max-iters", "2"]
    assert cli.main(argv) == 0, capsys.readouterr().err
    snap = {k: _snapshot(out / f"s{k}") for k in range(2)}
    assert (len(snap[0]), len(snap[1])) == (7, 5)
    f = root / "s0" / "000003.npz"
    _drop_last_point(f)  # a frame replaced by the user (one point fewer)
    (out / "s0" / "000006.npz").unlink()  # and one output missing, so the sequence has work
    rc = cli.main(argv)
    err = capsys.readouterr().err
    assert rc == 0, err
    # 000006 (missing), and the frames whose windows (3 scans) hold 000003: 000002 to 000004
    assert _rewritten(snap[0], out / "s0") == ["000002", "000003", "000004", "000006"]
    assert _rewritten(snap[1], out / "s1") == []


def test_written_dataset_sequence_recomputes_changed_inputs(tmp_path, capsys):
    """A dataset sequence whose outputs all exist is not skipped unchecked: its inputs are
    compared as ``floxels run SEQ`` compares them (lidar/dataset/run.py, issue 32); the frames
    whose windows hold an edited scan are written again, the other sequence is not touched, and
    a run with nothing changed writes nothing."""
    from floxels_ext.evaluation.seqio import save_sequence
    from floxels_ext.evaluation.sim import simulate_sequence

    root, out = tmp_path / "data", tmp_path / "out"
    for k in range(2):
        save_sequence(root / f"s{k}", simulate_sequence("crossing", 6 - k, k, beams=8, azimuth_steps=180))
    argv = ["run", str(root), "--out", str(out), "--device", "cpu", "--scans", "3", "--max-iters", "2"]
    assert cli.main(argv) == 0, capsys.readouterr().err
    snap = {k: _snapshot(out / f"s{k}") for k in range(2)}
    assert cli.main(argv) == 0
    err = capsys.readouterr().err
    assert "11 frames, 11 already done" in err and "(0 done, 2 skipped, 0 failed)" in err, err
    assert [_rewritten(snap[k], out / f"s{k}") for k in range(2)] == [[], []]
    f = root / "s0" / "000003.npz"
    _drop_last_point(f)  # a frame replaced by the user (one point fewer)
    assert cli.main(argv) == 0
    err = capsys.readouterr().err
    assert "11 frames, 7 already done" in err and "(1 done, 1 skipped, 0 failed)" in err, err
    assert err.count("inputs changed") == 1  # said once, by the sequence's own check
    # the frames whose windows (3 scans) hold 000003: 000002 to 000005 (the last frame's window is [3, 6))
    assert _rewritten(snap[0], out / "s0") == ["000002", "000003", "000004", "000005"]
    assert _rewritten(snap[1], out / "s1") == []
    # outputs written with other settings: each such sequence fails, as the plain run stops (--force recomputes)
    assert cli.main([*argv, "--max-iters", "3"]) == 1
    err = capsys.readouterr().err
    assert "s1/000000.npz was written with other settings" in err and "(0 done, 0 skipped, 2 failed)" in err, err
