"""``floxels export --format av2-submission`` on the shared Argoverse 2 pair (skipped without it):
a real ``floxels run`` over the pair laid out as an AV2 log, exported with the challenge's mask
definition; the files pass the official checks and the official evaluation (PyPI ``av2``,
``av2.evaluation.scene_flow``; skipped without it) scores them as ``floxels eval`` scores the
same points, to float16 precision. A run whose flow is the official label exports the label.
Runs that cannot give the files are refused before anything is written."""

from __future__ import annotations

import io
import json
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest

from floxels_ext import cli

pa = pytest.importorskip("pyarrow")
feather = pytest.importorskip("pyarrow.feather")

LOG = "7fab2350-7eaf-3b7e-a39d-6937a4c1bede"


@pytest.fixture(scope="module")
def pair(av2_pair_path):
    return dict(np.load(av2_pair_path))


@pytest.fixture(scope="module")
def log(pair, tmp_path_factory):
    """The pair as the Argoverse 2 log it came from: sweeps (x, y, z stored as float16, as in the
    log: the pair's float32 points are exactly those values) and city_SE3_egovehicle poses."""
    from scipy.spatial.transform import Rotation

    d = tmp_path_factory.mktemp("av2") / LOG
    (d / "sensors" / "lidar").mkdir(parents=True)
    rows = {k: [] for k in ("timestamp_ns", "qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m")}
    for k, ts in enumerate(pair["timestamps_ns"]):
        pc = pair[f"pc{k}"]
        assert np.array_equal(pc.astype(np.float16).astype(np.float32), pc)
        feather.write_feather(pa.table({"x": pc[:, 0].astype(np.float16), "y": pc[:, 1].astype(np.float16),
                                        "z": pc[:, 2].astype(np.float16),
                                        "intensity": pair[f"intensity{k}"].astype(np.uint8)}),
                              str(d / "sensors" / "lidar" / f"{int(ts)}.feather"))
        P = pair[f"pose{k}"]
        x, y, z, w = Rotation.from_matrix(P[:3, :3]).as_quat()
        for key, v in zip(rows, (int(ts), w, x, y, z, *P[:3, 3])):
            rows[key].append(v)
    feather.write_feather(pa.table(rows), str(d / "city_SE3_egovehicle.feather"))
    return d


@pytest.fixture(scope="module")
def run_dir(log, tmp_path_factory):
    out = tmp_path_factory.mktemp("run") / "flow"
    assert cli.main(["run", str(log), "--out", str(out), "--device", "cpu", "-q"]) == 0
    return out


def _challenge_mask(pair) -> np.ndarray:
    """The challenge's scored points (av2 utils.compute_eval_point_mask): |x|, |y| <= 50 m in the
    ego frame and not ground by the map (the pair's label ground)."""
    pc = pair["pc0"]
    return (np.abs(pc[:, 0]) <= 50) & (np.abs(pc[:, 1]) <= 50) & ~pair["is_ground0"]


def _write_masks(path: Path, entries: dict[str, np.ndarray]) -> Path:
    """A mask archive as make_mask_files.py writes it: <log>/<ts>.feather, one bool column 'mask'."""
    with zipfile.ZipFile(path, "w") as z:
        for name, mask in entries.items():
            buf = io.BytesIO()
            feather.write_feather(pa.table({"mask": mask}), buf)
            z.writestr(name, buf.getvalue())
    return path


@pytest.fixture(scope="module")
def masks(pair, tmp_path_factory):
    return _write_masks(tmp_path_factory.mktemp("masks") / "val-masks.zip",
                        {f"{LOG}/{int(pair['timestamps_ns'][0])}.feather": _challenge_mask(pair)})


def _export(run, out, *extra):
    return cli.main(["export", str(run), str(out), "--format", "av2-submission", *map(str, extra)])


def _read_submission(path: Path) -> dict:
    t = feather.read_table(str(path))
    return {c: t.column(c).to_numpy(zero_copy_only=False) for c in t.column_names}


def _object_motion(pair) -> np.ndarray:
    """The label without the ego motion, in sweep 0's frame (the flow floxels run writes)."""
    pc0, T = pair["pc0"].astype(np.float64), pair["ego1_T_ego0"]
    return (pc0 + pair["flow"].astype(np.float64) - T[:3, 3]) @ T[:3, :3] - pc0


def _f16_bound(v: np.ndarray) -> np.ndarray:
    """Per row, the largest |float16(v) - v| (half a float16 spacing per component)."""
    return 0.5 * np.linalg.norm(np.spacing(np.abs(v).astype(np.float16)).astype(np.float64), axis=1)


@pytest.mark.slow
def test_official_tools_accept_the_files_and_score_them_as_floxels_eval(pair, run_dir, masks, tmp_path, capsys):
    ev = pytest.importorskip("av2.evaluation.scene_flow.eval")
    msa = pytest.importorskip("av2.evaluation.scene_flow.make_submission_archive")
    pd = pytest.importorskip("pandas")
    out = tmp_path / "sub"
    assert _export(run_dir, out, "--masks", masks) == 0, capsys.readouterr().err
    msa.validate(out, masks)  # raises on a missing file, a wrong column, dtype or row count
    ts = int(pair["timestamps_ns"][0])
    with zipfile.ZipFile(out / "submission.zip") as z:
        assert z.namelist() == [f"{LOG}/{ts}.feather"]

    # the annotation file of make_annotation_files.py, from the official label
    m = _challenge_mask(pair)
    pts, label = pair["pc0"][m], pair["flow"][m]
    anno = tmp_path / "anno" / LOG
    anno.mkdir(parents=True)
    pd.DataFrame({"category_indices": pair["classes0"][m].astype(np.uint8),
                  "is_close": (np.abs(pts[:, :2]) <= 35.0).all(1), "is_dynamic": pair["dynamic0"][m],
                  "is_valid": pair["flow_valid"][m], "flow_tx_m": label[:, 0].astype(np.float16),
                  "flow_ty_m": label[:, 1].astype(np.float16), "flow_tz_m": label[:, 2].astype(np.float16),
                  }).to_feather(anno / f"{ts}.feather")
    official = ev.results_to_dict(ev.evaluate_zip(tmp_path / "anno", out / "submission.zip"))

    # floxels eval on the same points: the run's flow (per frame period = this pair's interval,
    # the run's only step) against the label's object motion; classes 0 = background, every
    # other category foreground (the challenge's FOREGROUND_BACKGROUND_BREAKDOWN)
    from floxels_ext.lidar.io.outputs import read_flow_output

    run = read_flow_output(run_dir / f"{ts}.npz")
    gt, pred = tmp_path / "gt", tmp_path / "pred"
    gt.mkdir()
    pred.mkdir()
    obj = _object_motion(pair)[m]
    np.savez(gt / "000000.npz", points=pts, flow=obj, classes=pair["classes0"][m].astype(np.int64),
             dynamic=pair["dynamic0"][m], ground=np.zeros(m.sum(), bool), pose=np.eye(4))
    np.savez(pred / "000000.npz", flow=run["flow"][m])
    cmap = tmp_path / "fg_bg.json"
    cmap.write_text(json.dumps({str(c): ("background" if c == 0 else "car") for c in range(31)}))
    ours = {}
    # the challenge's 'close' is |x|, |y| <= 35 m (make_annotation_files.py), floxels eval's box
    # (the 2024 evaluation's) max(|x|, |y|) < 35: the points lie on float16 values, some exactly
    # at 35 m and the next above at 35.03 m, so a box of 35.001 m selects the challenge's set
    for box, args in (("", ["--no-eval-box"]), ("/Close", ["--eval-box", "35.001"])):
        assert cli.main(["eval", str(pred), str(gt), "--all-points", "--categories", str(cmap),
                         "--json", str(tmp_path / "m.json"), *args]) == 0
        tw = json.loads((tmp_path / "m.json").read_text())["threeway_epe"]
        ours.update({f"EPE/Foreground/Dynamic{box}": tw["foreground_dynamic"],
                     f"EPE/Foreground/Static{box}": tw["foreground_static"],
                     f"EPE/Background/Static{box}": tw["background"]})
        if not box:
            ours["EPE 3-Way Average"] = tw["mean"]
    edge = np.abs(pts[:, :2]).max(1)
    assert np.any(edge == 35.0) and not np.any((edge > 35.0) & (edge < 35.001))

    # float16 precision: the submission and the annotation round every vector to float16
    sub = _read_submission(out / LOG / f"{ts}.feather")
    exported = np.stack([sub[c].astype(np.float64) for c in ("flow_tx_m", "flow_ty_m", "flow_tz_m")], 1)
    bound = _f16_bound(exported) + _f16_bound(label.astype(np.float64)) + 1e-6
    dyn, fg, close = pair["dynamic0"][m], pair["classes0"][m] > 0, (np.abs(pts[:, :2]) <= 35.0).all(1)
    subsets = {"EPE/Foreground/Dynamic": fg & dyn, "EPE/Foreground/Static": fg & ~dyn,
               "EPE/Background/Static": ~fg & ~dyn}
    for name, sel in list(subsets.items()):
        subsets[name + "/Close"] = sel & close
    for name, sel in subsets.items():
        assert abs(official[name] - ours[name]) <= bound[sel].mean(), (name, official[name], ours[name])
    assert abs(official["EPE 3-Way Average"] - ours["EPE 3-Way Average"]) <= \
        np.mean([bound[subsets[k]].mean() for k in ("EPE/Foreground/Dynamic", "EPE/Foreground/Static",
                                                      "EPE/Background/Static")])
    assert official["EPE/Foreground/Dynamic"] > 0.01  # a real estimate, not a trivially equal zero


def test_a_run_whose_flow_is_the_label_exports_the_label(pair, run_dir, masks, tmp_path):
    """The conventions (ego frame of sweep 0, ego motion added, metres over the pair): the
    object motion of the label, written as a run's flow, comes out as the label itself."""
    ts = int(pair["timestamps_ns"][0])
    perfect = tmp_path / "perfect"
    shutil.copytree(run_dir, perfect)
    z = dict(np.load(perfect / f"{ts}.npz"))
    z.update(flow=_object_motion(pair).astype(np.float32), mask=np.ones(len(pair["pc0"]), bool),
             dynamic=pair["dynamic0"])
    np.savez(perfect / f"{ts}.npz", **z)
    assert _export(perfect, tmp_path / "sub", "--masks", masks) == 0
    sub = _read_submission(tmp_path / "sub" / LOG / f"{ts}.feather")
    m = _challenge_mask(pair)
    assert set(sub) == {"flow_tx_m", "flow_ty_m", "flow_tz_m", "is_dynamic"}
    assert all(sub[c].dtype == np.float16 for c in ("flow_tx_m", "flow_ty_m", "flow_tz_m"))
    got = np.stack([sub[c] for c in ("flow_tx_m", "flow_ty_m", "flow_tz_m")], 1).astype(np.float64)
    want = pair["flow"][m].astype(np.float64)
    # the label's float32 object motion -> float16: within a float16 step of the label
    assert np.all(np.abs(got - want) <= np.spacing(np.abs(want).astype(np.float16)).astype(np.float64) + 1e-6)
    np.testing.assert_array_equal(sub["is_dynamic"], pair["dynamic0"][m])


def _rewrite(path: Path, **changes) -> None:
    z = dict(np.load(path))
    z.update(changes)
    np.savez(path, **z)


def test_refusals_write_nothing(pair, run_dir, masks, tmp_path, capsys):
    ts0, ts1 = (int(t) for t in pair["timestamps_ns"])
    out = tmp_path / "sub"

    def refused(run, *extra, says):
        rc = _export(run, out, *extra)
        err = capsys.readouterr().err
        assert rc == 2 and err.startswith("floxels: error: ") and says in err, err
        assert not out.exists() or not any(out.rglob("*")), sorted(out.rglob("*"))

    refused(run_dir, says="needs --masks")
    refused(run_dir, "--masks", tmp_path / "none.zip", says="no such file")
    # a sweep of another log: the leaderboard needs every one
    other = _write_masks(tmp_path / "two.zip", {f"{LOG}/{ts0}.feather": _challenge_mask(pair),
                                                "0a0a0a0a-other-log/315966265259836000.feather": np.ones(5, bool)})
    refused(run_dir, "--masks", other, says="no output for 1 of the 2 sweeps")
    # the last sweep has no next one: no ego motion to it
    refused(run_dir, "--masks", _write_masks(tmp_path / "last.zip", {f"{LOG}/{ts1}.feather": np.ones(
        len(pair["pc1"]), bool)}), says="no 'ego_motion'")
    # a mask of another length: not the same sweep file
    refused(run_dir, "--masks", _write_masks(tmp_path / "short.zip", {f"{LOG}/{ts0}.feather": np.ones(10, bool)}),
            says="covers 10 points")
    # ego motion not from the log's poses: another frame convention
    for k, (mode, source, says) in enumerate((
            ("identity", None, "--no-ego-motion"), ("frame", None, "poses stored in the frames"),
            ("table", "/odometry/poses_kiss_icp.txt", "poses from /odometry/poses_kiss_icp.txt"),
            ("table", "/other-log/city_SE3_egovehicle.feather", "poses from /other-log"))):
        bad = tmp_path / f"bad_{k}"
        shutil.copytree(run_dir, bad)
        for p in bad.glob("*.npz"):
            st = json.loads(str(np.load(p)["settings"]))
            _rewrite(p, settings=np.str_(json.dumps(dict(st, ego_motion=mode, pose_source=source))))
        refused(bad, "--masks", masks, says=says)
    # not an Argoverse 2 run: no timestamp, no log id
    plain = tmp_path / "plain"
    shutil.copytree(run_dir, plain)
    z = dict(np.load(plain / f"{ts0}.npz"))
    del z["timestamp_ns"]
    np.savez(plain / f"{ts0}.npz", **z)
    refused(plain, "--masks", masks, says="not the output of an Argoverse 2 sweep")
    refused(tmp_path / "nothing", "--masks", masks, says="does not exist")
    rc = cli.main(["export", str(run_dir), str(out), "--format", "opensceneflow", "--masks", str(masks)])
    assert rc == 2 and "--masks only applies to --format av2-submission" in capsys.readouterr().err


def test_partial_exports_what_the_run_has_and_says_so(pair, run_dir, tmp_path, capsys):
    ts0 = int(pair["timestamps_ns"][0])
    two = _write_masks(tmp_path / "two.zip", {f"{LOG}/{ts0}.feather": _challenge_mask(pair),
                                              "0a0a0a0a-other-log/315966265259836000.feather": np.ones(5, bool)})
    out = tmp_path / "sub"
    (out).mkdir()
    (out / "submission.zip").write_bytes(b"stale")
    assert _export(run_dir, out, "--masks", two, "--partial", "--zip", tmp_path / "part.zip") == 0
    err = capsys.readouterr().err
    assert "NOT a valid leaderboard submission" in err and "1 of the 2 sweeps" in err
    with zipfile.ZipFile(tmp_path / "part.zip") as z:
        assert z.namelist() == [f"{LOG}/{ts0}.feather"]
    assert (out / "submission.zip").read_bytes() == b"stale"  # --zip elsewhere: left alone


def test_opensceneflow_flow_of_a_perfect_run_is_the_label(pair, run_dir, tmp_path):
    """The training export uses the same convention: its 'flow' of the label's object motion is
    the label (float32), and the ego motion the trainer subtracts is the label's."""
    h5py = pytest.importorskip("h5py")
    ts0, ts1 = (str(int(t)) for t in pair["timestamps_ns"])
    perfect = tmp_path / "perfect"
    shutil.copytree(run_dir, perfect)
    _rewrite(perfect / f"{ts0}.npz", flow=_object_motion(pair).astype(np.float32),
             mask=np.ones(len(pair["pc0"]), bool))
    assert cli.main(["export", str(perfect), str(tmp_path / "h5"), "--format", "opensceneflow"]) == 0
    with h5py.File(tmp_path / "h5" / f"{LOG}.h5", "r") as f:
        assert sorted(f.keys()) == [ts0, ts1] and "flow" not in f[ts1]
        np.testing.assert_allclose(f[ts0]["flow"][:], pair["flow"], atol=2e-5)
        np.testing.assert_allclose(f[ts0]["ego_motion"][:], pair["ego1_T_ego0"], atol=1e-6)
        np.testing.assert_array_equal(f[ts0]["lidar"][:], pair["pc0"])
        p0, p1 = f[ts0]["pose"][:].astype(np.float64), f[ts1]["pose"][:].astype(np.float64)
    np.testing.assert_allclose(np.linalg.inv(p1) @ p0, pair["ego1_T_ego0"], atol=2e-5)
