"""Issue 45 through ``cli.main``: read-only places (item 8), empty names (item 9), output
hygiene (item 10). A fake method (instant) stands in for Floxels."""

import errno
import os

import pytest
from cli_doubles import main as _main
from cli_doubles import npy_frames as _npy_dir
from cli_doubles import fake, simulated  # noqa: F401  (fake: the --method fake fixture)

N = 4


@pytest.fixture
def seq():
    return simulated(N, 5)


@pytest.fixture
def read_only(monkeypatch, tmp_path):
    """``tmp_path/ro`` behaves as a read-only file system (errno 30, EROFS: not a
    PermissionError, which was the only kind caught): creating anything under it fails."""
    ro = tmp_path / "ro"
    ro.mkdir()
    (ro / "existing").mkdir()
    real_open, real_mkdir = os.open, os.mkdir

    def refuse(path):
        return str(os.path.abspath(path)).startswith(str(ro))

    def ro_open(path, flags, *a, **k):
        if flags & (os.O_CREAT | os.O_WRONLY | os.O_RDWR) and refuse(path):
            raise OSError(errno.EROFS, "Read-only file system", str(path))
        return real_open(path, flags, *a, **k)

    def ro_mkdir(path, *a, **k):
        if refuse(path):
            raise OSError(errno.EROFS, "Read-only file system", str(path))
        return real_mkdir(path, *a, **k)

    monkeypatch.setattr(os, "open", ro_open)
    monkeypatch.setattr(os, "mkdir", ro_mkdir)
    return ro


@pytest.mark.parametrize("where", ["new/sub", "existing"])
def test_out_in_a_read_only_place_is_refused_before_any_frame(seq, fake, tmp_path, capsys, read_only, where):
    d = _npy_dir(seq, tmp_path / "in")
    rc, cap = _main(["run", d, "--out", read_only / where, "--method", "fake", "--no-ego-motion", "--device", "cpu"],
                    capsys)
    assert rc == 2 and cap.err.startswith(f"floxels: error: --out {read_only / where}: cannot write"), cap.err
    assert "Read-only file system" in cap.err and fake == []  # found before computing, not after
    # a dataset's OUT root too
    _npy_dir(seq, tmp_path / "data" / "a")
    _npy_dir(seq, tmp_path / "data" / "b")
    rc, cap = _main(["run", tmp_path / "data", "--out", read_only / where, "--method", "fake", "--no-ego-motion",
                     "--device", "cpu"], capsys)
    assert rc == 2 and "Read-only file system" in cap.err and fake == []


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only directories")
def test_out_in_a_directory_without_write_permission(seq, fake, tmp_path, capsys):
    d = _npy_dir(seq, tmp_path / "in")
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    try:
        rc, cap = _main(["run", d, "--out", locked / "o", "--method", "fake", "--no-ego-motion", "--device", "cpu"],
                        capsys)
        assert rc == 2 and "cannot write" in cap.err and fake == []
    finally:
        locked.chmod(0o755)


def test_simulate_into_a_read_only_place_or_an_empty_name(tmp_path, capsys, read_only, monkeypatch):
    rc, cap = _main(["simulate", read_only / "s", "--small", "--frames", "1"], capsys)
    assert rc == 2 and f"OUT_DIR {read_only / 's'}: cannot write in {read_only}" in cap.err, cap.err
    monkeypatch.chdir(tmp_path)
    rc, cap = _main(["simulate", "", "--small", "--frames", "1"], capsys)  # wrote into the current directory
    assert rc == 2 and "OUT_DIR is empty" in cap.err and not list(tmp_path.glob("*.npz"))


def test_an_empty_preset_is_refused_like_the_api(seq, fake, tmp_path, capsys):
    from floxels_ext import FloxelsConfig

    with pytest.raises(ValueError):
        FloxelsConfig.preset("")
    d = _npy_dir(seq, tmp_path / "in")
    rc, cap = _main(["run", d, "--out", tmp_path / "o", "--preset", "", "--no-ego-motion", "--device", "cpu"], capsys)
    assert rc == 2 and "unknown --preset ''" in cap.err and not (tmp_path / "o").exists()


def _run(args, capsys):
    return _main(["run", *args, "--device", "cpu", "--method", "fake"], capsys)


def test_force_on_a_subset_with_other_settings_and_eval_of_the_mix(seq, fake, tmp_path, capsys):
    from floxels_ext.evaluation.seqio import save_sequence

    save_sequence(tmp_path / "sim", seq)
    out = tmp_path / "o"
    rc, cap = _run([tmp_path / "sim", "--out", out, "--scans", "3"], capsys)
    assert rc == 0, cap.err
    rc, cap = _main(["eval", out, tmp_path / "sim"], capsys)
    assert rc == 0, cap.err
    rc, cap = _run([tmp_path / "sim", "--out", out, "--scans", "3", "--force", "--frames", "1:2",
                    "--dynamic-threshold", "0.2"], capsys)
    assert rc == 0 and "floxels: warning: --force recomputes --frames 1:2 only; 3 other output(s)" in cap.err
    assert "dynamic_threshold" in cap.err
    rc, cap = _main(["eval", out, tmp_path / "sim"], capsys)  # scored the mix without a word before
    assert rc == 2 and "mixes outputs written with 2 different settings: 000000, 000002..000003 and 000001" \
        in cap.err and "dynamic_threshold: 0.05 vs 0.2" in cap.err, cap.err
    rc, cap = _main(["eval", out, tmp_path / "sim", "--frames", "2:4"], capsys)  # one part: fine
    assert rc == 0, cap.err


def test_outputs_of_deleted_frames_are_set_aside(seq, fake, tmp_path, capsys):
    d = _npy_dir(seq, tmp_path / "in")
    out = tmp_path / "o"
    rc, cap = _run([d, "--out", out, "--no-ego-motion", "--scans", "3"], capsys)
    assert rc == 0
    (d / "000003.npy").unlink()  # a bad sweep deleted from the input
    rc, cap = _run([d, "--out", out, "--no-ego-motion", "--scans", "3"], capsys)
    assert rc == 0 and "moved 1 output(s) of frames no longer in the input" in cap.err and "000003.npz" in cap.err
    assert sorted(p.name for p in out.glob("*.npz")) == ["000000.npz", "000001.npz", "000002.npz"]
    assert (out / "orphaned" / "000003.npz").is_file()  # kept, out of the run's outputs
    assert "recomputing 1 frame(s) whose inputs changed" in cap.err  # 000002, whose window lost 000003


def test_a_broken_symlink_frame_fails_by_name_and_is_no_dropped_frame(seq, fake, tmp_path, capsys):
    d = _npy_dir(seq, tmp_path / "in")
    (d / "000002.npy").unlink()
    (d / "000002.npy").symlink_to(tmp_path / "gone.npy")
    rc, cap = _run([d, "--out", tmp_path / "o", "--no-ego-motion", "--scans", "3"], capsys)
    assert rc == 1 and "000002.npy: broken symbolic link" in cap.err and "1 failed" in cap.err, cap.err
    assert "gaps in the frame numbers" not in cap.err  # was taken for a dropped frame (offsets of 2)


def test_summary_through_a_symlink_is_written_through(seq, fake, tmp_path, capsys):
    d = _npy_dir(seq, tmp_path / "in")
    (tmp_path / "reports").mkdir()
    target = tmp_path / "reports" / "summary.json"
    target.write_text("{}")
    link = tmp_path / "summary.json"
    link.symlink_to(target)
    rc, cap = _run([d, "--out", tmp_path / "o", "--no-ego-motion", "--scans", "3", "--summary", link], capsys)
    assert rc == 0, cap.err
    assert link.is_symlink() and '"written": 4' in target.read_text()
