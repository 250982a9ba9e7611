"""What `floxels eval` scores (issue 30, item 3): by default only the points the run optimised
(its 'mask'), all with --all-points; partial runs and --frames A:B; --categories av2 refused on
simulated classes; --json an existing directory refused before any work. Through cli.main."""

import json

import numpy as np
import pytest

from floxels_ext import cli
from floxels_ext.evaluation.seqio import frame_path, write_frame

N_FRAMES, N = 5, 8


def _gt(d, simulated=True):
    """Frames like `floxels simulate` writes: 2 moving car points, 6 static background points."""
    d.mkdir(parents=True, exist_ok=True)
    for i in range(N_FRAMES):
        flow = np.zeros((N, 3), np.float32)
        flow[:2] = [1.0, 0, 0]
        write_frame(frame_path(d, i), points=np.arange(3 * N, dtype=np.float32).reshape(N, 3) + i, flow=flow,
                    classes=np.array([1, 1] + [0] * (N - 2)), ground=np.zeros(N, bool),
                    dynamic=np.linalg.norm(flow, axis=1) > 0.05, pose=np.eye(4))
    if simulated:
        (d / "sequence.json").write_text(json.dumps({"generator": "floxels_ext.evaluation.sim", "scene": "x"}))


def _pred(d, frames):
    """Frames like `floxels run` writes: exact flow on the optimised points (mask), 0 on one
    car point and one static point the run cropped."""
    d.mkdir(parents=True, exist_ok=True)
    for i in frames:
        flow = np.zeros((N, 3), np.float32)
        flow[0] = [1.0, 0, 0]
        mask = np.ones(N, bool)
        mask[[1, 5]] = False
        np.savez(frame_path(d, i), flow=flow, mask=mask, method=np.array("floxels"),
                 options=np.array(json.dumps({"num_scans": 3})))


def _main(capsys, argv):
    rc = cli.main(argv)
    cap = capsys.readouterr()
    assert "Traceback" not in cap.err
    return rc, cap


def test_scores_only_optimised_points_by_default(tmp_path, capsys):
    _gt(tmp_path / "gt")
    _pred(tmp_path / "pred", range(N_FRAMES))
    rc, cap = _main(capsys, ["eval", str(tmp_path / "pred"), str(tmp_path / "gt"), "--json", str(tmp_path / "m.json")])
    assert rc == 0, cap.err
    m = json.loads((tmp_path / "m.json").read_text())
    assert m["dynamic_epe"] == 0.0 and m["static_epe"] == 0.0  # the unoptimised zero-flow car point is not scored
    assert m["num_points"] == N_FRAMES * (N - 2) and m["scored_points"] == "optimised"
    assert m["not_optimised_count"] == 2 * N_FRAMES
    assert "only the points the run optimised" in cap.out and "--all-points" in cap.out
    rc, cap = _main(capsys, ["eval", str(tmp_path / "pred"), str(tmp_path / "gt"), "--all-points",
                             "--json", str(tmp_path / "a.json")])
    a = json.loads((tmp_path / "a.json").read_text())
    assert rc == 0 and a["num_points"] == N_FRAMES * N and a["scored_points"] == "all"
    assert a["dynamic_epe"] == pytest.approx(0.5)  # one of the two car points has flow 0: EPE 1
    assert "every point" in cap.out


def test_partial_run_and_frames_range(tmp_path, capsys):
    _gt(tmp_path / "gt")
    _pred(tmp_path / "pred", [1, 2, 3])  # floxels run --frames 1:4
    rc, cap = _main(capsys, ["eval", str(tmp_path / "pred"), str(tmp_path / "gt"), "--json", str(tmp_path / "m.json")])
    assert rc == 0, cap.err
    m = json.loads((tmp_path / "m.json").read_text())
    assert m["frames_scored"] == [1, 2, 3] and m["gt_frames"] == N_FRAMES and m["num_frames"] == 3
    assert "frames 000001..000003 of the ground truth's 5" in cap.out
    rc, cap = _main(capsys, ["eval", str(tmp_path / "pred"), str(tmp_path / "gt"), "--frames", "2:4",
                             "--json", str(tmp_path / "m.json")])
    assert rc == 0 and json.loads((tmp_path / "m.json").read_text())["frames_scored"] == [2, 3]
    rc, cap = _main(capsys, ["eval", str(tmp_path / "pred"), str(tmp_path / "gt"), "--frames", "0:3"])
    assert rc == 2 and "--frames 0:3: 1 of the 3 chosen frames have no prediction" in cap.err
    assert "000000.npz" in cap.err


def test_av2_categories_refused_on_simulated_classes(tmp_path, capsys):
    _gt(tmp_path / "gt")
    _pred(tmp_path / "pred", range(N_FRAMES))
    rc, cap = _main(capsys, ["eval", str(tmp_path / "pred"), str(tmp_path / "gt"), "--categories", "av2"])
    assert rc == 2 and cap.err.startswith("floxels: error: --categories av2:")
    assert "'floxels simulate' sequence" in cap.err and "ANIMAL" in cap.err


def test_json_output_path_checked_before_the_work(tmp_path, capsys):
    _gt(tmp_path / "gt")
    _pred(tmp_path / "pred", range(N_FRAMES))
    (tmp_path / "dir.json").mkdir()
    rc, cap = _main(capsys, ["eval", str(tmp_path / "pred"), str(tmp_path / "gt"), "--json", str(tmp_path / "dir.json")])
    assert rc == 2 and "is an existing directory" in cap.err
    assert cap.out == ""  # refused before scoring anything
    assert not list(tmp_path.glob(".*.tmp")) and not list((tmp_path / "dir.json").iterdir())
