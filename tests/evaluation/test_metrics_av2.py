"""Our AV2 bucketed / three-way metrics against the official evaluation package.

The OFFICIAL numbers below were computed with ``bucketed-scene-flow-eval`` 2.0.25 (PyPI; not a
dependency of this project, installed in a separate venv) on the shared Argoverse 2 pair, by
feeding its own ``BucketedEPEEvaluator`` / ``ThreeWayEPEEvaluator`` (built by
``datasets.argoverse2.dataset._make_av2_evaluator`` with the AV2 defaults: ``CATEGORY_MAP``,
``BUCKETED_METACATAGORIES`` / ``THREEWAY_EPE_METACATAGORIES``, distance thresholds [35, inf]) one
frame: pc0's non-ground points with an identity pose (sweep 0's ego frame is the evaluation's
global frame for a pair), the object flow (official label minus ego motion, in sweep 0's frame),
class ids = AV2 label class - 1 (the package counts -1 = BACKGROUND, 0 = ANIMAL, ...), and the
predictions of ``_predictions`` below; results read from ``compute_results(
return_distance_threshold=35 | inf)`` and its ``mean_average_results_<d>.json``. (open3d, which
the package imports for visualisation only, was replaced by a stub: it needs libusb.)
"""

import json
import math

import numpy as np
import pytest

from floxels_ext import cli
from floxels_ext.evaluation.metrics import evaluate_sequence
from floxels_ext.evaluation.protocol import AV2_CATEGORIES, AV2_CATEGORY_MAP, AV2_IGNORED, AV2_META_CLASSES, IGNORE, META_CLASSES

NAN = float("nan")
# (prediction, box) -> official per meta-class (static EPE, dynamic normalised EPE) and the means
OFFICIAL = {
    ("zero", 35): {
        "background": (0.0008226498098985585, NAN), "car": (0.006004422369306157, 1.0),
        "other_vehicle": (NAN, NAN), "pedestrian": (0.005357311962658292, 1.0),
        "wheeled_vru": (0.004070733340044721, NAN), "mean": (0.004063779370476932, 1.0),
        "threeway": {"background": 0.0008226498098985585, "foreground_static": 0.006085175628576756,
                     "foreground_dynamic": 0.6740044184710484},
    },
    ("zero", None): {
        "background": (0.0008226546406181171, NAN), "car": (0.00601472489188341, 1.0),
        "other_vehicle": (0.0070904268480386536, 1.0), "pedestrian": (0.005482610686612304, 1.0),
        "wheeled_vru": (0.003702538785895841, NAN), "mean": (0.004622591170609665, 1.0),
        "threeway": {"background": 0.0008226546406181171, "foreground_static": 0.006100947530069223,
                     "foreground_dynamic": 0.6636608054948484},
    },
    ("perturbed", 35): {
        "background": (0.05145914349222038, NAN), "car": (0.051318272677500644, 0.3197673013332205),
        "other_vehicle": (NAN, NAN), "pedestrian": (0.05183320034563412, 0.5095646494438614),
        "wheeled_vru": (0.052206762207467027, NAN), "mean": (0.05170434468070555, 0.41466597538854094),
        "threeway": {"background": 0.05145914349222038, "foreground_static": 0.051358042668333624,
                     "foreground_dynamic": 0.08313226676218599},
    },
    ("perturbed", None): {
        "background": (0.051457488082623064, NAN), "car": (0.05132231261328736, 0.24251229828761464),
        "other_vehicle": (0.05145274712378156, 0.1453273097282624), "pedestrian": (0.05237850738572416, 0.32286186885020524),
        "wheeled_vru": (0.05189614185421621, NAN), "mean": (0.051701439411926474, 0.23690049228869406),
        "threeway": {"background": 0.051457488082623064, "foreground_static": 0.05137391266876514,
                     "foreground_dynamic": 0.08235350320286884},
    },
}
OFFICIAL_NUM_POINTS = 81855  # non-ground points of pc0


@pytest.fixture(scope="module")
def av2(av2_pair_path):
    d = np.load(av2_pair_path)
    pc0 = d["pc0"].astype(np.float64)
    T = d["ego1_T_ego0"]
    gt = (pc0 + d["flow"].astype(np.float64) - T[:3, 3]) @ T[:3, :3] - pc0  # object motion, sweep 0 frame
    frame = {"points": pc0, "flow": gt, "classes": d["classes0"].astype(np.int64), "ground": d["is_ground0"],
             "pose": np.eye(4)}
    return frame


def _predictions(frame) -> dict[str, np.ndarray]:
    keep = ~frame["ground"]
    g = frame["flow"][keep]
    i = np.arange(len(g), dtype=np.float64)
    pert = np.zeros_like(frame["flow"])
    pert[keep] = 0.9 * g + 0.05 * np.stack([np.sin(i), np.cos(1.3 * i), 0.5 * np.sin(0.7 * i)], 1)
    return {"zero": np.zeros_like(frame["flow"]), "perturbed": pert}


def _close(a, b, tol=1e-12):
    return (math.isnan(a) and math.isnan(b)) or abs(a - b) <= tol


@pytest.mark.parametrize("pred_name,box", list(OFFICIAL))
def test_equals_official_evaluation(av2, pred_name, box):
    pred = _predictions(av2)[pred_name]
    r = evaluate_sequence([pred], [av2], category_map="av2", eval_box=box)
    off = OFFICIAL[(pred_name, box)]
    for c in META_CLASSES:
        assert _close(r["static_epe_per_class"][c], off[c][0]), (c, r["static_epe_per_class"][c], off[c][0])
        assert _close(r["dynamic_normalized_epe"][c], off[c][1]), (c, r["dynamic_normalized_epe"][c], off[c][1])
    assert _close(r["mean_static_epe"], off["mean"][0]) and _close(r["mean_dynamic_normalized_epe"], off["mean"][1])
    for k, v in off["threeway"].items():
        assert _close(r["threeway_epe"][k], v), (k, r["threeway_epe"][k], v)
    assert r["ignored_count"] == 14  # BOLLARD and CONSTRUCTION_CONE points
    if box is None:
        assert r["num_points"] + r["ignored_count"] == OFFICIAL_NUM_POINTS


def test_box_matters_on_the_shared_pair(av2):
    pred = _predictions(av2)["perturbed"]
    inside = evaluate_sequence([pred], [av2], category_map="av2", eval_box=35.0)
    everywhere = evaluate_sequence([pred], [av2], category_map="av2")
    assert inside["outside_box_count"] > 5000 and everywhere["outside_box_count"] == 0
    assert inside["mean_dynamic_normalized_epe"] == pytest.approx(0.41466597538854094, abs=1e-12)
    assert everywhere["mean_dynamic_normalized_epe"] == pytest.approx(0.23690049228869406, abs=1e-12)


def test_av2_category_map_matches_the_official_lists():
    assert len(AV2_CATEGORIES) == 31 and AV2_CATEGORIES[0] == "BACKGROUND"
    listed = [c for cats in AV2_META_CLASSES.values() for c in cats] + list(AV2_IGNORED)
    assert sorted(listed) == sorted(AV2_CATEGORIES)  # every category exactly once
    assert AV2_CATEGORY_MAP[AV2_CATEGORIES.index("REGULAR_VEHICLE")] == META_CLASSES.index("car")
    assert AV2_CATEGORY_MAP[AV2_CATEGORIES.index("STROLLER")] == META_CLASSES.index("pedestrian")
    assert AV2_CATEGORY_MAP[AV2_CATEGORIES.index("TRUCK_CAB")] == META_CLASSES.index("other_vehicle")
    assert AV2_CATEGORY_MAP[AV2_CATEGORIES.index("STOP_SIGN")] == IGNORE
    assert AV2_CATEGORY_MAP[0] == 0


def test_cli_eval_av2_categories_and_box(av2, tmp_path, capsys):
    """`floxels eval --categories av2` reads AV2 label classes from disk and applies the box."""
    gt, pred = tmp_path / "gt", tmp_path / "pred"
    gt.mkdir()
    pred.mkdir()
    np.savez_compressed(gt / "000000.npz", points=av2["points"].astype(np.float32), flow=av2["flow"].astype(np.float32),
                        classes=av2["classes"].astype(np.uint8), ground=av2["ground"], pose=av2["pose"])
    np.savez_compressed(pred / "000000.npz", flow=_predictions(av2)["perturbed"].astype(np.float32))
    out = tmp_path / "m.json"
    assert cli.main(["eval", str(pred), str(gt), "--categories", "av2", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "35 m evaluation box" in text and "ignored categories" in text
    m = json.loads(out.read_text())
    assert m["eval_box"] == 35.0 and m["category_map"] == "av2"
    assert m["mean_dynamic_normalized_epe"] == pytest.approx(0.41466597538854094, rel=1e-4)  # float32 on disk
    assert cli.main(["eval", str(pred), str(gt), "--categories", "av2", "--no-eval-box", "--json", str(out)]) == 0
    assert json.loads(out.read_text())["mean_dynamic_normalized_epe"] == pytest.approx(0.23690049228869406, rel=1e-4)
    # a dataset marked as AV2 in sequence.json gets the AV2 map (and with it the box) by default
    (gt / "sequence.json").write_text(json.dumps({"dataset": "av2"}))
    assert cli.main(["eval", str(pred), str(gt), "--json", str(out)]) == 0
    assert json.loads(out.read_text())["eval_box"] == 35.0
    # without a map, AV2 class ids are not meta-classes: a clear error, not a crash
    (gt / "sequence.json").unlink()
    assert cli.main(["eval", str(pred), str(gt)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("floxels: error: ") and "classes" in err and "--categories av2" in err
