"""``floxels run`` / ``show`` / ``accumulate`` user errors of issue 30, through ``cli.main`` (the
entry point): frames with no point left after cropping, stray far points, output paths that are
existing directories, numeric options, ``run -q``, ``show``'s input hash. A fake method (instant,
exact) stands in for Floxels."""

import json

import numpy as np
import pytest

from floxels_ext import cli, methods

N = 4


@pytest.fixture(scope="module")
def seq():
    from floxels_ext.evaluation.sim import simulate_sequence

    return simulate_sequence("crossing", N, 2, beams=16, azimuth_steps=360)


@pytest.fixture
def fake(monkeypatch):
    def est(scans, frames, device, options, callback, times=None):
        for f in frames:
            callback(f, np.tile(np.float32([0.4, 0, 0]), (len(scans[f]), 1)))

    monkeypatch.setitem(methods._REGISTRY, "fake", methods.Method("fake", "test double", est))


def _npy_dir(seq, d, shift=(0.0, 0.0, 0.0), edit=None):
    d.mkdir(parents=True, exist_ok=True)
    for i, fr in enumerate(seq.frames):
        p = fr.points + np.asarray(shift)
        if edit is not None:
            p = edit(i, p)
        np.save(d / f"{i:06d}.npy", p.astype(np.float32))
    return d


def _run(args, capsys):
    rc = cli.main(["run", *map(str, args), "--device", "cpu"])
    return rc, capsys.readouterr()


def test_world_frame_with_no_ego_motion_fails_every_emptied_frame_by_name(seq, fake, tmp_path, capsys):
    # world-frame points 300 m from the world origin read with --no-ego-motion: the 50 m crop
    # around the origin empties every frame (before: all-zero flow, "0 failed", exit 0)
    d = _npy_dir(seq, tmp_path / "in", shift=(300.0, 0.0, 0.0))
    rc, cap = _run([d, "--out", tmp_path / "out", "--method", "fake", "--no-ego-motion"], capsys)
    assert rc == 1
    assert "000002.npy: no point left to optimise after cropping" in cap.err
    assert "Likely a wrong frame" in cap.err and "--no-ego-motion measures from the world origin" in cap.err
    assert f"{N} failed ({N} with no point left after cropping)" in cap.err
    summary = json.loads((tmp_path / "out" / "run_summary.json").read_text())
    assert summary["failed"] == N and summary["no_points_after_crop"] == [f"{i:06d}" for i in range(N)]
    assert not list((tmp_path / "out").glob("*.npz"))  # no all-zero flow passed off as a result


def test_one_scan_beyond_max_range_fails_that_frame_only(seq, fake, tmp_path, capsys):
    d = _npy_dir(seq, tmp_path / "in", edit=lambda i, p: p + np.array([500.0, 0, 0]) if i == 1 else p)
    rc, cap = _run([d, "--out", tmp_path / "out", "--method", "fake", "--no-ego-motion"], capsys)
    assert rc == 1 and "1 failed (1 with no point left after cropping)" in cap.err
    assert "000001.npy: no point left" in cap.err and "000002.npy: no point" not in cap.err
    assert sorted(p.name for p in (tmp_path / "out").glob("*.npz")) == ["000000.npz", "000002.npz", "000003.npz"]
    # the same files with the crop widened: the frame is estimated
    rc, cap = _run([d, "--out", tmp_path / "out2", "--method", "fake", "--no-ego-motion", "--max-range", "none",
                    "--max-height", "none"], capsys)
    assert rc == 0, cap.err
