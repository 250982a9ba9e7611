import json
import os
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np

import floxels_ext
import pytest

from floxels_ext import cli
from floxels_ext.evaluation.seqio import Frame, SequenceFormatError, frame_path, load_sequence, read_frame, write_frame
from floxels_ext.lidar.viz.bev_png import bev_image, bev_png, hsv_to_rgb, write_png

# the subprocess must import the same floxels_ext as the tests (installed or in-place build)
PYTHON_DIR = str(Path(floxels_ext.__file__).resolve().parents[1])


def _frame(n, seed=0):
    rng = np.random.default_rng(seed)
    flow = np.zeros((n, 3), np.float32)
    flow[: n // 2] = [0.5, 0, 0]
    return Frame(points=rng.normal(size=(n, 3)).astype(np.float32), flow=flow,
                 classes=np.r_[np.ones(n // 2), np.zeros(n - n // 2)].astype(np.int32),
                 dynamic=np.linalg.norm(flow, axis=1) > 0.05, ground=np.zeros(n, bool),
                 instance=np.r_[np.zeros(n // 2), -np.ones(n - n // 2)].astype(np.int32), pose=np.eye(4))


def _write_gt(d, sizes=(10, 12)):
    for i, n in enumerate(sizes):
        write_frame(frame_path(d, i), _frame(n, i))


# ---------------------------------------------------------------- seqio
def test_write_is_atomic_and_names(tmp_path):
    _write_gt(tmp_path)
    assert sorted(os.listdir(tmp_path)) == ["000000.npz", "000001.npz"]  # no temp files left
    with np.load(tmp_path / "000000.npz") as z:
        assert set(z.files) == {"points", "flow", "classes", "instance", "dynamic", "ground", "pose"}
        assert z["points"].dtype == np.float32


def test_read_errors_name_the_file(tmp_path):
    np.savez_compressed(tmp_path / "000000.npz", flow=np.zeros((3, 3)))
    with pytest.raises(SequenceFormatError, match=r"000000\.npz.*missing key.*points"):
        read_frame(tmp_path / "000000.npz")
    np.savez_compressed(tmp_path / "000000.npz", points=np.zeros((3, 3)), flow=np.zeros((4, 3)))
    with pytest.raises(SequenceFormatError, match=r"000000\.npz.*'flow' has 4"):
        read_frame(tmp_path / "000000.npz")
    np.savez_compressed(tmp_path / "000000.npz", points=np.zeros((3, 2)))
    with pytest.raises(SequenceFormatError, match=r"\(N, 3\)"):
        read_frame(tmp_path / "000000.npz")
    np.savez_compressed(tmp_path / "000000.npz", points=np.zeros((2, 3)), classes=np.array([0, 9]))
    with pytest.raises(SequenceFormatError, match="classes"):
        read_frame(tmp_path / "000000.npz")
    (tmp_path / "000000.npz").write_bytes(b"not a zip")
    with pytest.raises(SequenceFormatError, match="cannot read"):
        read_frame(tmp_path / "000000.npz")
    with pytest.raises(SequenceFormatError, match="missing frame file"):
        read_frame(tmp_path / "000005.npz")


def test_list_frames_gaps_and_empty(tmp_path):
    with pytest.raises(SequenceFormatError, match="does not exist"):
        load_sequence(tmp_path / "nope")
    with pytest.raises(SequenceFormatError, match="no frame files"):
        load_sequence(tmp_path)
    write_frame(frame_path(tmp_path, 0), _frame(3))
    write_frame(frame_path(tmp_path, 2), _frame(3))
    with pytest.raises(SequenceFormatError, match=r"missing frame .*000001\.npz"):
        load_sequence(tmp_path)


def test_minimal_frame_roundtrip(tmp_path):
    pts = np.arange(12, dtype=np.float32).reshape(4, 3)
    write_frame(tmp_path / "000000.npz", points=pts)
    seq = load_sequence(tmp_path)
    assert len(seq) == 1 and seq.meta == {}
    np.testing.assert_array_equal(seq[0].points, pts)
    assert seq[0].flow is None and seq[0].classes is None
    with pytest.raises(ValueError, match="unknown frame keys"):
        write_frame(tmp_path / "x.npz", points=pts, colour=pts)


# ---------------------------------------------------------------- CLI
def test_simulate_then_eval_perfect(tmp_path, capsys):
    gt = tmp_path / "gt"
    assert cli.main(["simulate", str(gt), "--scene", "parking", "--seed", "2", "--frames", "2", "--small"]) == 0
    assert "wrote 2 frames" in capsys.readouterr().out
    seq = load_sequence(gt)
    assert len(seq) == 2 and seq.meta["scene"] == "parking"
    for i, f in enumerate(seq):
        write_frame(frame_path(tmp_path / "pred", i), flow=f.flow)
    out_json = tmp_path / "m.json"
    assert cli.main(["eval", str(tmp_path / "pred"), str(gt), "--json", str(out_json)]) == 0
    text = capsys.readouterr().out
    assert "dynamic" in text and "three-way" in text and "pedestrian" in text
    m = json.loads(out_json.read_text())
    for key in ("dynamic_epe", "dynamic_acc5", "dynamic_acc10", "dynamic_angle", "static_epe", "static_acc5",
                "static_acc10", "threeway_epe", "dynamic_normalized_epe", "mean_dynamic_normalized_epe",
                "mean_static_epe"):
        assert key in m
    assert m["dynamic_epe"] == 0 and m["mean_dynamic_normalized_epe"] == 0
    assert m["dynamic_normalized_epe"]["background"] is None  # NaN -> null
    # refuses to overwrite without --force
    assert cli.main(["simulate", str(gt), "--frames", "1", "--small"]) == 2
    assert "--force" in capsys.readouterr().err
    assert cli.main(["simulate", str(gt), "--frames", "1", "--small", "--force"]) == 0
    assert len(load_sequence(gt)) == 1


def _eval_err(capsys, pred, gt, *extra):
    rc = cli.main(["eval", str(pred), str(gt), *extra])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("floxels: error: ") and "Traceback" not in err
    return err


def test_eval_user_errors(tmp_path, capsys):
    gt, pred = tmp_path / "gt", tmp_path / "pred"
    _write_gt(gt)
    assert "does not exist" in _eval_err(capsys, pred, gt)
    write_frame(frame_path(pred, 0), flow=np.zeros((10, 3)))
    # a partial run scores the frames it has (issue 30); --frames asks for all of its range
    assert cli.main(["eval", str(pred), str(gt)]) == 0
    assert "frames 000000 of the ground truth's 2" in capsys.readouterr().out
    err = _eval_err(capsys, pred, gt, "--frames", "0:2")
    assert "no prediction" in err and "000001.npz" in err
    write_frame(frame_path(pred, 1), flow=np.zeros((11, 3)))
    err = _eval_err(capsys, pred, gt)
    assert "000001.npz" in err and "11 points" in err and "12" in err
    np.savez_compressed(frame_path(pred, 1), velocity=np.zeros((12, 3)))
    err = _eval_err(capsys, pred, gt)
    assert "000001.npz" in err and "flow" in err
    write_frame(frame_path(pred, 1), flow=np.zeros((12, 3)))
    np.savez_compressed(frame_path(gt, 1), points=np.zeros((12, 3)))  # ground truth without flow
    err = _eval_err(capsys, pred, gt)
    assert str(frame_path(gt, 1)) in err and "flow" in err
    write_frame(frame_path(pred, 2), flow=np.zeros((12, 3)))
    assert "only 2" in _eval_err(capsys, pred, gt)


def test_eval_numbers_and_subprocess(tmp_path):
    gt, pred = tmp_path / "gt", tmp_path / "pred"
    _write_gt(gt, sizes=(4,))
    write_frame(frame_path(pred, 0), flow=np.array([[0.5, 0.1, 0], [0.5, 0, 0], [0, 0, 0], [0, 0.2, 0]]))
    env = {**os.environ, "PYTHONPATH": PYTHON_DIR + os.pathsep + os.environ.get("PYTHONPATH", "")}
    cmd = [sys.executable, "-m", "floxels_ext", "eval", str(pred), str(gt), "--json", str(tmp_path / "m.json")]
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0, r.stderr
    m = json.loads((tmp_path / "m.json").read_text())
    assert m["dynamic_epe"] == pytest.approx(0.05)
    assert m["static_epe"] == pytest.approx(0.1)
    assert m["threeway_epe"]["background"] == pytest.approx(0.1)
    r = subprocess.run([sys.executable, "-m", "floxels_ext", "eval", str(tmp_path / "x"), str(gt)],
                       capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 2 and "floxels: error:" in r.stderr and "Traceback" not in r.stderr


def test_registry_adds_subcommands(capsys):
    def add_parser(sub):
        p = sub.add_parser("hello")
        p.add_argument("--name", default="x")
        p.set_defaults(func=lambda a: print("hi", a.name) or 3)

    cli.register(add_parser)
    try:
        assert cli.main(["hello", "--name", "y"]) == 3
        assert "hi y" in capsys.readouterr().out
    finally:
        cli._EXTRA.remove(add_parser)
    with pytest.raises(SystemExit) as e:
        cli.main(["bogus"])
    assert e.value.code == 2


# ---------------------------------------------------------------- viz
def _decode_png(path):
    data = Path(path).read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, chunks = 8, {}
    while pos < len(data):
        (n,) = struct.unpack(">I", data[pos:pos + 4])
        tag, body = data[pos + 4:pos + 8], data[pos + 8:pos + 8 + n]
        assert struct.unpack(">I", data[pos + 8 + n:pos + 12 + n])[0] == zlib.crc32(tag + body) & 0xFFFFFFFF
        chunks[tag] = chunks.get(tag, b"") + body
        pos += 12 + n
    w, h, depth, ctype = struct.unpack(">IIBB", chunks[b"IHDR"][:10])
    assert (depth, ctype) == (8, 2) and b"IEND" in chunks
    raw = np.frombuffer(zlib.decompress(chunks[b"IDAT"]), np.uint8).reshape(h, 1 + 3 * w)
    assert np.all(raw[:, 0] == 0)
    return raw[:, 1:].reshape(h, w, 3)


def test_png_roundtrip(tmp_path):
    img = np.random.default_rng(0).integers(0, 256, (7, 5, 3), dtype=np.uint8)
    write_png(tmp_path / "a.png", img)
    np.testing.assert_array_equal(_decode_png(tmp_path / "a.png"), img)
    with pytest.raises(ValueError):
        write_png(tmp_path / "b.png", np.zeros((4, 4)))


def test_bev_png_content(tmp_path):
    pts = np.array([[0.0, 0, 0.5], [5.0, 5.0, 1.0]])
    flow = np.array([[2.0, 0, 0], [0, 0, 0]])  # one moving point heading +x
    nxt = np.array([[-5.0, -5.0, 0.0]])
    bev_png(tmp_path / "v.png", pts, flow, nxt, center=(0, 0), extent=10, resolution=0.1)
    img = _decode_png(tmp_path / "v.png")
    assert img.shape == (200, 200, 3)
    bg = np.array([12, 12, 16])
    # pixel of (5, 5): column 150, row 50 -> coloured by height, not background
    assert not np.array_equal(img[50, 150], bg)
    # the next scan's point (-5, -5) is red
    np.testing.assert_array_equal(img[150, 50], [235, 50, 50])
    # the flow segment from (0, 0) to (2, 0) runs along row 100, hue of heading 0 is cyan
    seg = img[100, 101:119]
    assert np.all(seg[:, 0] < 60) and np.all(seg[:, 1] > 200) and np.all(seg[:, 2] > 200)
    # outside the segment it is background
    np.testing.assert_array_equal(img[100, 130], bg)


def test_bev_edge_cases(tmp_path):
    img = bev_image(np.zeros((0, 3)), extent=5, resolution=1.0)
    assert img.shape == (10, 10, 3)
    img = bev_image(np.zeros((3, 3)), np.zeros((3, 3)), color_by="grey", extent=5, resolution=1.0)
    assert (img == 150).all(axis=-1).sum() == 1
    with pytest.raises(ValueError):
        bev_image(np.zeros((3, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError):
        bev_image(np.zeros((3, 3)), color_by="rainbow")
    rgb = hsv_to_rgb(np.array([0.0, 1 / 3, 2 / 3]), 1.0, 1.0)
    np.testing.assert_allclose(rgb, np.eye(3), atol=1e-12)


def test_bev_of_simulated_scan(tmp_path):
    from floxels_ext.evaluation.sim import simulate_sequence

    seq = simulate_sequence("highway", 2, seed=0, small=True)
    f = seq.frames[0]
    p = bev_png(tmp_path / "h.png", f.points, f.flow, seq.frames[1].points, center=f.pose[:2, 3])
    img = _decode_png(p)
    assert img.shape == (800, 800, 3)
    coloured = np.any(img != [12, 12, 16], axis=-1).mean()
    assert 0.01 < coloured < 0.9
