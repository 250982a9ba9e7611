"""Issue 45 item 4 through ``cli.main``: ``floxels show --frame`` and ``floxels accumulate FRAME``
pick the frame they are told, by name or by its index among the run's input frames, and a
frame without output is an error that says so (it used to draw the next output)."""

import pytest
from cli_doubles import main as _main
from cli_doubles import fake, npy_frames, simulated  # noqa: F401  (fake: the --method fake fixture)

N = 6


@pytest.fixture
def seq():
    return simulated(N, 3)


def _npy_dir(seq, d, name="{i:06d}", broken=()):
    npy_frames(seq, d, name=name)
    for i in broken:
        (d / f"{name.format(i=i)}.npy").write_bytes(b"not a numpy file")
    return d


def test_a_failed_frame_is_not_replaced_by_the_next(seq, fake, tmp_path, capsys):
    d = _npy_dir(seq, tmp_path / "in", broken=(2,))
    run = tmp_path / "run"
    rc, cap = _main(["run", d, "--out", run, "--method", "fake", "--no-ego-motion", "--device", "cpu", "-q"], capsys)
    assert rc == 1  # 000002 failed
    png = tmp_path / "x.png"
    for frame in ("000002", "2", "-4"):  # by name, by index, from the end: the same frame, no output
        rc, cap = _main(["show", run, "--frame", frame, "--png", png], capsys)
        assert rc == 2 and "frame 000002" in cap.err and "has no output: it failed in the run" in cap.err, cap.err
        assert "000002.npy" in cap.err and not png.exists()  # the run's reason
    rc, cap = _main(["accumulate", run, "2", "--out", tmp_path / "a.ply"], capsys)
    assert rc == 2 and "frame 000002 (index 2) has no output" in cap.err and not (tmp_path / "a.ply").exists()
    rc, cap = _main(["show", run, "--frame", "3", "--png", png], capsys)
    assert rc == 0 and png.is_file() and "frame 000003" in cap.out, cap.out
    rc, cap = _main(["show", run, "--frame", "9", "--png", png], capsys)
    assert rc == 2 and "frame index 9 is out of range" in cap.err and "6 frames (0 .. 5)" in cap.err
    rc, cap = _main(["show", run, "--frame", "000009", "--png", png], capsys)
    assert rc == 2 and "has no frame named '000009'" in cap.err
    # accumulate around frame 3: its neighbour 000002 has no output: left out, said, the others
    # keep their true time offsets (000001 is 2 frames before, not 1)
    ply = tmp_path / "b.ply"
    rc, cap = _main(["accumulate", run, "000003", "--out", ply, "--neighbours", "2"], capsys)
    assert rc == 0 and "left out 000002" in cap.out and "frames 000001..000005" in cap.out, cap.out
    from floxels_ext.lidar.viz.accumulate import accumulate_run

    pts, off, names = accumulate_run(run, "3", neighbours=2, use_flow=False, note=lambda m: None)
    assert names == ["000001", "000003", "000004", "000005"] and sorted(set(off.tolist())) == [-2, 0, 1, 2]


def test_a_frames_subset_run_counts_the_input_frames(seq, fake, tmp_path, capsys):
    d = _npy_dir(seq, tmp_path / "in")
    run = tmp_path / "run"
    rc, cap = _main(["run", d, "--out", run, "--method", "fake", "--no-ego-motion", "--device", "cpu",
                     "--frames", "3:5", "-q"], capsys)
    assert rc == 0, cap.err
    png = tmp_path / "x.png"
    rc, cap = _main(["show", run, "--frame", "3", "--png", png], capsys)  # was refused
    assert rc == 0 and "frame 000003" in cap.out
    rc, cap = _main(["show", run, "--frame", "1", "--png", png.with_name("y.png")], capsys)  # drew 000004
    assert rc == 2 and "frame 000001 (index 1) has no output: it was not estimated" in cap.err
    assert not png.with_name("y.png").exists()
    rc, cap = _main(["show", run, "--png", png], capsys)  # default: the first output
    assert rc == 0 and "frame 000003" in cap.out


def test_names_that_read_as_other_indices(seq, fake, tmp_path, capsys):
    # frames named 1 .. 6: "2" is the name of index 1; the name wins, and a note says so
    d = _npy_dir(seq, tmp_path / "in", name="{i}")
    for i in range(N - 1, -1, -1):
        (d / f"{i}.npy").rename(d / f"{i + 1}.npy")
    run = tmp_path / "run"
    rc, cap = _main(["run", d, "--out", run, "--method", "fake", "--no-ego-motion", "--device", "cpu", "-q"], capsys)
    assert rc == 0, cap.err
    rc, cap = _main(["show", run, "--frame", "2", "--png", tmp_path / "x.png"], capsys)
    assert rc == 0 and "the frame named 2; the frame of index 2 is 3" in cap.out and "frame 2," in cap.out
