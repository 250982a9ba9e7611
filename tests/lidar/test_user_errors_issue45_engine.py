"""Issue 45 through ``cli.main``, inside ``floxels run``'s pipeline: frames none of whose support
scans can be read (item 3), an optimisation that diverged (item 9), a failed frame's error
printed once under ``-q`` (item 10). One sequence and the dataset pipeline alike."""

import json

import pytest
from cli_doubles import main, npy_frames, register_fake, simulated


@pytest.fixture
def seq():
    return simulated(4, 6)


def _broken(seq, d, broken=(1,)):
    npy_frames(seq, d)
    for i in broken:
        (d / f"{i:06d}.npy").write_bytes(b"not a numpy file")
    return d


def test_frames_without_a_readable_support_scan_fail_with_the_reason(seq, tmp_path, capsys):
    # the example: --scans 2, the next frame's file broken: frame 0 was written with zero
    # flow (nothing dynamic, counted as written); with the real method, a few iterations
    d = _broken(seq, tmp_path / "in")
    out = tmp_path / "o"
    rc, cap = main(["run", d, "--out", out, "--scans", "2", "--max-iters", "5", "--no-ego-motion", "--device", "cpu"],
                   capsys)
    assert rc == 1 and "1 frame(s) written" in cap.err and "3 failed" in cap.err, cap.err
    assert sorted(p.name for p in out.glob("*.npz")) == ["000003.npz"]  # its support, 000002, is fine
    failures = {f["frame"]: f["message"] for f in json.loads((out / "run_summary.json").read_text())["failures"]}
    for name in ("000000", "000002"):
        assert "no support scan" in failures[name] and "000001.npy" in failures[name], failures[name]
    assert "no support scan" not in failures["000001"]  # its own file is the reason


def test_dataset_frames_without_support_fail_alike(seq, tmp_path, capsys, monkeypatch):
    from floxels_ext.estimator.api import window_for

    register_fake(monkeypatch, support_frames=lambda i, n, o: [j for j in range(*window_for(i, n, 2)) if j != i])
    _broken(seq, tmp_path / "data" / "a")
    npy_frames(seq, tmp_path / "data" / "b")
    rc, cap = main(["run", tmp_path / "data", "--out", tmp_path / "o", "--scans", "2", "--method", "fake",
                    "--no-ego-motion", "--device", "cpu"], capsys)
    assert rc == 1, cap.err
    summary = json.loads((tmp_path / "o" / "a" / "run_summary.json").read_text())
    assert summary["written"] == 1 and summary["failed"] == 3
    assert sum("no support scan" in f["message"] for f in summary["failures"]) == 2
    assert json.loads((tmp_path / "o" / "b" / "run_summary.json").read_text())["written"] == 4


def test_a_diverged_optimisation_fails_its_frames(seq, tmp_path, capsys):
    d = npy_frames(seq, tmp_path / "in")
    out = tmp_path / "o"
    rc, cap = main(["run", d, "--out", out, "--scans", "3", "--frames", "1:3", "--max-iters", "30",
                    "--option", "lr=1e9", "--no-ego-motion", "--device", "cpu"], capsys)
    # all-zero flow written as a result, exit 0, before
    assert rc == 1 and "2 failed" in cap.err and not list(out.glob("*.npz")), cap.err
    assert "000001.npy: the optimisation diverged: its loss rose from" in cap.err and "lower lr (lr=1e+09)" in cap.err
    assert cap.err.count("the optimisation diverged") == 2  # once a frame, in the final list; no second warning


def test_a_failed_frame_is_printed_once_under_q(seq, tmp_path, capsys, monkeypatch):
    register_fake(monkeypatch)
    d = _broken(seq, tmp_path / "in", broken=(3,))
    rc, cap = main(["run", d, "--out", tmp_path / "o", "--scans", "3", "--method", "fake", "--no-ego-motion",
                    "--device", "cpu", "-q"], capsys)
    assert rc == 1 and cap.err.count("000003.npy") == 1, cap.err
    rc, cap = main(["run", d, "--out", tmp_path / "o2", "--scans", "3", "--method", "fake", "--no-ego-motion",
                    "--device", "cpu"], capsys)
    assert rc == 1 and "floxels: error:" in cap.err  # without -q it is also said as it happens


def test_a_failed_frame_is_printed_once_under_q_in_a_dataset(seq, tmp_path, capsys, monkeypatch):
    register_fake(monkeypatch)
    _broken(seq, tmp_path / "data" / "a", broken=(3,))
    npy_frames(seq, tmp_path / "data" / "b")
    rc, cap = main(["run", tmp_path / "data", "--out", tmp_path / "o", "--scans", "3", "--method", "fake",
                    "--no-ego-motion", "--device", "cpu", "-q"], capsys)
    assert rc == 1 and cap.err.count("000003.npy") == 1, cap.err
