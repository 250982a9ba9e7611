"""`floxels eval` user errors: swapped arguments, NaN predictions, the angle column for static
points and zero flow, bad --categories / --eval-box values."""

import json

import numpy as np
import pytest

from floxels_ext import cli
from floxels_ext.evaluation.seqio import frame_path, write_frame


def _gt(d, n=6):
    """Two ground-truth frames like `floxels simulate` writes: a moving car and static background."""
    for i in range(2):
        flow = np.zeros((n, 3), np.float32)
        flow[:2] = [1.0, 0, 0]
        write_frame(frame_path(d, i), points=np.arange(3 * n, dtype=np.float32).reshape(n, 3), flow=flow,
                    classes=np.array([1, 1] + [0] * (n - 2)), ground=np.zeros(n, bool),
                    dynamic=np.linalg.norm(flow, axis=1) > 0.05, pose=np.eye(4))


def _pred(d, flows, nan_at=None):
    """Frames like `floxels run` writes: flow, points, and the method/options record."""
    for i, f in enumerate(flows):
        f = np.array(f, np.float32)
        if nan_at is not None and nan_at[0] == i:
            f[nan_at[1]] = np.nan
        d.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(frame_path(d, i), flow=f, points=np.zeros_like(f), mask=np.ones(len(f), bool),
                            method=np.array("floxels"), options=np.array(json.dumps({"num_scans": 3})))


def _err(capsys, argv):
    rc = cli.main(argv)
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("floxels: error: ") and "Traceback" not in err, err
    return err


def test_swapped_arguments_are_an_error_naming_both(tmp_path, capsys):
    gt, pred = tmp_path / "sim", tmp_path / "out"
    _gt(gt)
    _pred(pred, [np.zeros((6, 3))] * 2)
    assert cli.main(["eval", str(pred), str(gt)]) == 0  # the right order works
    capsys.readouterr()
    err = _err(capsys, ["eval", str(gt), str(pred)])
    assert "swapped" in err and str(gt) in err and str(pred) in err and "method" in err
    # a prediction directory given as ground truth, whatever PRED is
    err = _err(capsys, ["eval", str(pred), str(pred)])
    assert "GT_DIR" in err and "not ground truth" in err


def test_nan_prediction_is_rejected_naming_the_frame_file(tmp_path, capsys):
    gt, pred = tmp_path / "gt", tmp_path / "pred"
    _gt(gt)
    _pred(pred, [np.zeros((6, 3))] * 2, nan_at=(1, 4))
    err = _err(capsys, ["eval", str(pred), str(gt)])
    assert str(frame_path(pred, 1)) in err and "NaN" in err and "point 4" in err
    # inf is as bad, in a bare flow-only prediction too
    f = np.zeros((6, 3), np.float32)
    f[0, 2] = np.inf
    np.savez_compressed(frame_path(pred, 1), flow=f)
    err = _err(capsys, ["eval", str(pred), str(gt)])
    assert str(frame_path(pred, 1)) in err and "point 0" in err


def test_angle_column_for_zero_flow_and_static_points(tmp_path, capsys):
    gt, pred = tmp_path / "gt", tmp_path / "pred"
    _gt(gt)
    _pred(pred, [np.zeros((6, 3))] * 2)
    out = tmp_path / "m.json"
    assert cli.main(["eval", str(pred), str(gt), "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "1.571" not in text and "1.5708" not in text  # no pi/2 for undefined angles
    static_row = next(line for line in text.splitlines() if line.startswith("static"))
    dynamic_row = next(line for line in text.splitlines() if line.startswith("dynamic"))
    assert static_row.split()[-1] == "-" and dynamic_row.split()[-1] == "-"
    assert "only where both exceed 0.05 m/frame" in text and "0 of 4 dynamic" in text
    m = json.loads(out.read_text())
    assert m["static_angle"] is None and m["dynamic_angle"] is None
    assert m["dynamic_angle_count"] == 0 and m["static_angle_count"] == 0
    # a prediction with motion gets an angle for its dynamic points, still none for static ones
    flows = [np.zeros((6, 3)) for _ in range(2)]
    for f in flows:
        f[:2] = [1.0, 1.0, 0]  # 45 degrees off
    _pred(pred, flows)
    assert cli.main(["eval", str(pred), str(gt), "--json", str(out)]) == 0
    m = json.loads(out.read_text())
    assert m["dynamic_angle"] == pytest.approx(np.pi / 4) and m["dynamic_angle_count"] == 4
    assert m["static_angle"] is None


def test_bad_categories_and_box_options(tmp_path, capsys):
    gt, pred = tmp_path / "gt", tmp_path / "pred"
    _gt(gt)
    _pred(pred, [np.zeros((6, 3))] * 2)
    assert "no such JSON file" in _err(capsys, ["eval", str(pred), str(gt), "--categories", str(tmp_path / "x.json")])
    bad = tmp_path / "bad.json"
    bad.write_text('{"0": "background", "1": "spaceship"}')
    assert "spaceship" in _err(capsys, ["eval", str(pred), str(gt), "--categories", str(bad)])
    bad.write_text("[1, 2")
    assert "not valid JSON" in _err(capsys, ["eval", str(pred), str(gt), "--categories", str(bad)])
    partial = tmp_path / "partial.json"
    partial.write_text('{"0": "background"}')  # class 1 is missing from the map
    err = _err(capsys, ["eval", str(pred), str(gt), "--categories", str(partial)])
    assert "[1]" in err and "category map" in err
    good = tmp_path / "good.json"
    good.write_text('{"0": "background", "1": null}')  # ignore the car
    out = tmp_path / "m.json"
    assert cli.main(["eval", str(pred), str(gt), "--categories", str(good), "--json", str(out)]) == 0
    m = json.loads(out.read_text())
    assert m["ignored_count"] == 4 and m["dynamic_count"] == 0
    with pytest.raises(SystemExit) as e:  # refused when parsed (cli_types.positive_float)
        cli.main(["eval", str(pred), str(gt), "--eval-box", "-3"])
    assert e.value.code == 2 and "argument --eval-box: must be a finite number > 0" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # argparse: the two box options exclude each other
        cli.main(["eval", str(pred), str(gt), "--eval-box", "10", "--no-eval-box"])


def test_dataset_category_ids_go_through_the_sequence_reader(tmp_path, capsys):
    """With --categories the ground truth's classes are dataset ids, read by ``seqio.read_frame``
    like every frame (any integers kept); classes that are not integers are refused naming the file."""
    gt, pred = tmp_path / "gt", tmp_path / "pred"
    _pred(pred, [np.zeros((6, 3))] * 2)
    gt.mkdir()
    cmap = tmp_path / "map.json"
    cmap.write_text('{"0": "background", "17": null}')
    for classes in (np.array([17, 17, 0, 0, 0, 0]), np.full(6, 17.0)):
        for i in range(2):
            np.savez_compressed(frame_path(gt, i), points=np.arange(18, dtype=np.float32).reshape(6, 3),
                                flow=np.zeros((6, 3), np.float32), classes=classes)
        if classes.dtype.kind == "i":
            assert cli.main(["eval", str(pred), str(gt), "--categories", str(cmap)]) == 0
            capsys.readouterr()
        else:
            err = _err(capsys, ["eval", str(pred), str(gt), "--categories", str(cmap)])
            assert "000000.npz: 'classes' must be (6,) integers" in err
