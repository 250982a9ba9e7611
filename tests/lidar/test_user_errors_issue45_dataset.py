"""Issue 45 item 7 through ``cli.main``: a dataset's sequences are found at any depth, stray
frame files never hide the sequences below them, and earlier outputs are not inputs."""

import pytest
from cli_doubles import main as _main
from cli_doubles import npy_frames as _frames
from cli_doubles import register_fake, simulated

FAST = ["--device", "cpu", "--scans", "3", "--method", "fake", "--no-ego-motion"]


@pytest.fixture
def seq():
    return simulated(3, 4)


@pytest.fixture(autouse=True)
def fake(monkeypatch):
    return register_fake(monkeypatch)


def test_sequences_at_any_depth(seq, tmp_path, capsys):
    root = tmp_path / "data"
    _frames(seq, root / "a")
    _frames(seq, root / "b/c/d/e/f/g")  # depth 6: skipped without a word before (4 levels at most)
    (root / "loop").symlink_to(root, target_is_directory=True)  # a link back up: followed once
    rc, cap = _main(["run", root, "--out", tmp_path / "o", *FAST], capsys)
    assert rc == 0 and "2 sequences" in cap.err, cap.err
    assert sorted(p.relative_to(tmp_path / "o").as_posix() for p in (tmp_path / "o").rglob("000001.npz")) == \
        ["a/000001.npz", "b/c/d/e/f/g/000001.npz"]
    # the outputs of that run, inside the root, are not sequences of a later run
    rc, cap = _main(["run", root, "--out", root / "flow2", *FAST], capsys)
    assert rc == 0 and "2 sequences" in cap.err, cap.err
    rc, cap = _main(["run", tmp_path, "--out", tmp_path / "o3", *FAST], capsys)
    assert rc == 0 and "2 sequences" in cap.err, cap.err  # data/flow2/... and o/... (outputs) left out
    assert sorted(p.parent.relative_to(tmp_path / "o3").as_posix() for p in (tmp_path / "o3").rglob("000001.npz")) \
        == ["data/a", "data/b/c/d/e/f/g"]


def test_stray_frame_files_at_a_root_do_not_hide_its_sequences(seq, tmp_path, capsys):
    root = tmp_path / "data"
    _frames(seq, root / "s1")
    _frames(seq, root / "s2")
    _frames(seq, root, n=2)  # two stray frames: the root used to run as one 2-frame sequence, exit 0
    rc, cap = _main(["run", root, "--out", tmp_path / "o", *FAST], capsys)
    assert rc == 2 and f"{root} holds 2 frame file(s) (000000.npy, 000001.npy) and 2 sequence(s)" in cap.err
    assert "(s1, s2)" in cap.err and "Move the stray frame files away" in cap.err
    assert not (tmp_path / "o").exists()
    # the same one level down
    for p in root.glob("*.npy"):
        p.unlink()
    _frames(seq, root / "s1" / "deeper")
    rc, cap = _main(["run", root, "--out", tmp_path / "o", *FAST], capsys)
    assert rc == 2 and f"{root / 's1'} holds 3 frame file(s)" in cap.err and "s1/deeper" in cap.err
