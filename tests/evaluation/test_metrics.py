import math

import numpy as np
import pytest

from floxels_ext.evaluation.metrics import (
    BucketedEPE,
    angle_errors,
    bucketed_epe,
    evaluate_sequence,
    flow_metrics,
    threeway_epe,
)
from floxels_ext.evaluation.seqio import Frame

JSON_KEYS = {
    "dynamic_epe", "dynamic_acc5", "dynamic_acc10", "dynamic_angle", "static_epe", "static_acc5",
    "static_acc10", "threeway_epe", "dynamic_normalized_epe", "mean_dynamic_normalized_epe", "mean_static_epe",
}


def test_flow_metrics_hand_computed():
    gt = np.array([
        [1.0, 0, 0],  # dynamic
        [1.0, 0, 0],  # dynamic
        [0.0, 2.0, 0],  # dynamic
        [0.0, 0, 0],  # static
        [0.0, 0, 0],  # static
        [0.01, 0, 0],  # static (below 0.05)
    ])
    pred = np.array([
        [1.04, 0, 0],  # epe 0.04: abs<0.05 -> acc5, acc10
        [1.0, 0.08, 0],  # epe 0.08 (rel 8%): not acc5, acc10
        [0.0, 1.5, 0],  # epe 0.5 (rel 25%): outlier, angle 0
        [0.0, 0, 0],  # epe 0
        [0.0, 0.4, 0],  # epe 0.4 -> outlier, not acc; angle pi/2 (gt zero)
        [0.01, 0.01, 0],  # epe 0.01; rel 100% -> acc5 by abs, outlier by rel
    ])
    m = flow_metrics(pred, gt)
    assert m["dynamic_count"] == 3 and m["static_count"] == 3
    assert m["dynamic_epe"] == pytest.approx((0.04 + 0.08 + 0.5) / 3)
    assert m["dynamic_acc5"] == pytest.approx(1 / 3)
    assert m["dynamic_acc10"] == pytest.approx(2 / 3)
    assert m["dynamic_outliers"] == pytest.approx(1 / 3)
    assert m["dynamic_angle"] == pytest.approx((0 + math.atan2(0.08, 1.0) + 0) / 3)
    assert m["dynamic_angle_count"] == 3
    assert m["static_epe"] == pytest.approx((0 + 0.4 + 0.01) / 3)
    assert m["static_acc5"] == pytest.approx(2 / 3)
    assert m["static_acc10"] == pytest.approx(2 / 3)
    assert m["static_outliers"] == pytest.approx(2 / 3)
    # static points: gt at most 0.05 m, so no direction to compare against (not pi/2, not 0)
    assert math.isnan(m["static_angle"]) and m["static_angle_count"] == 0
    assert m["all_count"] == 6


def test_relative_criteria():
    gt = np.array([[3.0, 0, 0]])
    m = flow_metrics(np.array([[3.12, 0, 0]]), gt)  # epe 0.12, rel 4%
    assert m["dynamic_acc5"] == 1 and m["dynamic_acc10"] == 1 and m["dynamic_outliers"] == 0
    m = flow_metrics(np.array([[3.25, 0, 0]]), gt)  # epe 0.25, rel 8.3%
    assert m["dynamic_acc5"] == 0 and m["dynamic_acc10"] == 1 and m["dynamic_outliers"] == 0


def test_masks_and_empty_subsets():
    gt = np.array([[1.0, 0, 0], [0.0, 0, 0]])
    pred = np.zeros((2, 3))
    m = flow_metrics(pred, gt, dynamic_mask=[False, False])
    assert math.isnan(m["dynamic_epe"]) and m["dynamic_count"] == 0
    assert m["static_epe"] == pytest.approx(0.5)
    m = flow_metrics(pred, gt, valid_mask=[False, True])
    assert m["all_count"] == 1 and math.isnan(m["dynamic_epe"])
    with pytest.raises(ValueError, match="points"):
        flow_metrics(np.zeros((3, 3)), gt)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        flow_metrics(np.zeros((2, 2)), gt)


def test_angle_defined_only_where_both_vectors_move():
    p = np.array([[1.0, 0, 0], [0, 0, 0], [0, 0, 0], [1, 1, 0], [-1, 0, 0], [0.04, 0, 0], [0, 0.06, 0]])
    g = np.array([[0.0, 2, 0], [0, 0, 0], [1, 0, 0], [2, 2, 0], [1, 0, 0], [1, 0, 0], [0.06, 0, 0]])
    nan = float("nan")
    np.testing.assert_allclose(angle_errors(p, g), [math.pi / 2, nan, nan, 0, math.pi, nan, math.pi / 2], atol=1e-7)
    np.testing.assert_allclose(angle_errors(p, g, min_norm=0.0)[[1, 2, 5]], [nan, nan, 0.0], atol=1e-7)
    # zero flow everywhere: no angle error is defined, reported as NaN with a count of 0 (not pi/2)
    m = flow_metrics(np.zeros((4, 3)), np.array([[1.0, 0, 0], [0, 0, 0], [0, 0.5, 0], [0, 0, 0]]))
    assert math.isnan(m["dynamic_angle"]) and m["dynamic_angle_count"] == 0
    assert math.isnan(m["static_angle"]) and m["static_angle_count"] == 0


def test_non_finite_predictions_are_rejected():
    gt = np.zeros((4, 3))
    pred = np.zeros((4, 3))
    pred[2, 1] = np.nan
    for fn in (lambda: flow_metrics(pred, gt), lambda: threeway_epe(pred, gt, np.zeros(4)),
               lambda: BucketedEPE().update(pred, gt, np.zeros(4)), lambda: angle_errors(pred, gt)):
        with pytest.raises(ValueError, match=r"pred has 1 non-finite .*point 2"):
            fn()
    frames = _frames()
    preds = [np.zeros((3, 3)), np.array([[0, 0.5, 0], [np.inf, 0, 0]])]
    with pytest.raises(ValueError, match=r"predicted flow of frame 1 has 1 non-finite"):
        evaluate_sequence(preds, frames)


def test_category_map_and_eval_box():
    # classes are dataset ids: 7 -> car, 9 -> ignored, 0 -> background
    frames = [Frame(points=np.array([[1.0, 0, 0], [2, 0, 0], [40, 0, 0], [0, -50, 0]], np.float32),
                    flow=np.array([[1.0, 0, 0], [0, 0, 0], [1, 0, 0], [0, 0, 0]], np.float32),
                    classes=np.array([7, 9, 7, 0]), pose=np.eye(4))]
    preds = [np.array([[0.5, 0, 0], [3, 0, 0], [0, 0, 0], [0, 0.2, 0]])]
    cmap = {0: "background", 7: "car", 9: None}
    r = evaluate_sequence(preds, frames, category_map=cmap)
    assert r["ignored_count"] == 1 and r["num_points"] == 3 and r["category_map"] == "custom"
    assert r["dynamic_normalized_epe"]["car"] == pytest.approx(0.75)  # (0.5 + 1.0) / 2 in one bucket, speed 1
    r = evaluate_sequence(preds, frames, category_map=cmap, eval_box=35.0)
    assert r["outside_box_count"] == 2 and r["num_points"] == 1 and r["eval_box"] == 35.0
    assert r["dynamic_normalized_epe"]["car"] == pytest.approx(0.5)
    # the box is in the scan's own frame: a world pose moves it along
    moved = Frame(points=frames[0].points + np.float32([100, 0, 0]), flow=frames[0].flow,
                  classes=frames[0].classes, pose=np.array([[1, 0, 0, 100], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]))
    assert evaluate_sequence(preds, [moved], category_map=cmap, eval_box=35.0)["num_points"] == 1
    with pytest.raises(ValueError, match=r"class id\(s\) \[9\] are not in the category map"):
        evaluate_sequence(preds, frames, category_map={0: "background", 7: "car"})
    with pytest.raises(ValueError, match="category_map"):
        evaluate_sequence(preds, frames)  # ids > 4 without a map
    with pytest.raises(ValueError, match="meta-class"):
        evaluate_sequence(preds, frames, category_map={0: "bus"})


def test_threeway():
    gt = np.array([[1.0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0]])
    pred = np.array([[0.5, 0, 0], [0.2, 0, 0], [0, 0.1, 0], [0, 0.3, 0]])
    classes = np.array([1, 3, 0, 0])
    t = threeway_epe(pred, gt, classes)
    assert t["foreground_dynamic"] == pytest.approx(0.5)
    assert t["foreground_static"] == pytest.approx(0.2)
    assert t["background"] == pytest.approx(0.2)
    assert t["mean"] == pytest.approx(0.3)
    # background is scored on its static points, ignored (-1) points nowhere
    t = threeway_epe(np.zeros((3, 3)), np.array([[1.0, 0, 0], [0, 0, 0], [2, 0, 0]]), np.array([0, 0, -1]))
    assert t["background"] == 0 and math.isnan(t["foreground_static"]) and t["mean"] == 0
    t = threeway_epe(pred[2:], gt[2:], classes[2:])
    assert math.isnan(t["foreground_dynamic"]) and t["mean"] == pytest.approx(0.2)


def test_bucketed_hand_computed():
    acc = BucketedEPE()
    assert acc.count.shape == (5, 51)
    # car: one static point (speed 0, epe 0.1); moving points in two buckets
    #   bucket [0.48, 0.52): speeds 0.5 and 0.5, epes 0.1 and 0.3 -> mean 0.2 / 0.5 = 0.4
    #   overflow bucket: speed 3.0, epe 0.6 -> 0.2     => dynamic normalized = (0.4 + 0.2) / 2
    gt = np.array([[0, 0, 0], [0.5, 0, 0], [0, 0.5, 0], [3.0, 0, 0]])
    pred = gt + np.array([[0.1, 0, 0], [0.1, 0, 0], [0.3, 0, 0], [0, 0.6, 0]])
    acc.update(pred[:2], gt[:2], [1, 1])
    acc.update(pred[2:], gt[2:], [1, 1])  # accumulation over frames
    # pedestrian: only one moving point, speed 0.04 exactly (bucket 1), epe 0.02 -> 0.5
    acc.update(np.array([[0.06, 0, 0]]), np.array([[0.04, 0, 0]]), [3])
    # background: static only, epes 0.0 and 0.2 -> 0.1
    acc.update(np.array([[0, 0, 0], [0, 0.2, 0]]), np.zeros((2, 3)), [0, 0])
    r = acc.compute()
    assert r["static_epe"]["car"] == pytest.approx(0.1)
    assert r["static_epe"]["background"] == pytest.approx(0.1)
    assert math.isnan(r["static_epe"]["pedestrian"])
    assert r["dynamic_normalized_epe"]["car"] == pytest.approx(0.3)
    assert r["dynamic_normalized_epe"]["pedestrian"] == pytest.approx(0.5)
    assert math.isnan(r["dynamic_normalized_epe"]["background"])
    assert r["mean_dynamic_normalized_epe"] == pytest.approx(0.4)
    assert r["mean_static_epe"] == pytest.approx(0.1)
    r2 = bucketed_epe([pred], [gt], [[1, 1, 1, 1]])
    assert r2["dynamic_normalized_epe"]["car"] == pytest.approx(0.3)
    with pytest.raises(ValueError, match="classes"):
        acc.update(pred, gt, [0, 1, 7, 0])
    before = acc.count.sum()
    acc.update(pred, gt, [-1, -1, -1, -1])  # IGNORE
    assert acc.count.sum() == before


def test_zero_prediction_has_normalized_epe_one():
    acc = BucketedEPE()
    rng = np.random.default_rng(0)
    gt = rng.normal(size=(200, 3)) * 0.8
    acc.update(np.zeros_like(gt), gt, rng.integers(1, 5, 200))
    r = acc.compute()
    for name in ("car", "other_vehicle", "pedestrian", "wheeled_vru"):
        assert r["dynamic_normalized_epe"][name] == pytest.approx(1.0)


def _frames():
    f0 = Frame(points=np.zeros((3, 3), np.float32), flow=np.array([[1.0, 0, 0], [0, 0, 0], [0, 0, 0]], np.float32),
               classes=np.array([1, 0, 0]), ground=np.array([False, False, True]))
    f1 = Frame(points=np.zeros((2, 3), np.float32), flow=np.array([[0, 0.5, 0], [0, 0, 0]], np.float32),
               classes=np.array([3, 1]))
    return [f0, f1]


def test_evaluate_sequence_keys_and_values():
    frames = _frames()
    preds = [np.array([[0.9, 0, 0], [0, 0.1, 0], [5, 5, 5]]), np.array([[0, 0.5, 0], [0.2, 0, 0]])]
    r = evaluate_sequence(preds, frames)
    assert JSON_KEYS <= set(r)
    assert r["num_points"] == 4  # the ground point is excluded
    assert r["dynamic_epe"] == pytest.approx(0.05)
    assert r["static_epe"] == pytest.approx(0.15)
    assert r["threeway_epe"]["foreground_static"] == pytest.approx(0.2)
    assert r["threeway_epe"]["background"] == pytest.approx(0.1)
    assert r["dynamic_normalized_epe"]["car"] == pytest.approx(0.1)
    assert r["dynamic_normalized_epe"]["pedestrian"] == pytest.approx(0.0)
    assert r["mean_dynamic_normalized_epe"] == pytest.approx(0.05)
    assert r["mean_static_epe"] == pytest.approx(0.15)  # background 0.1, car 0.2
    r = evaluate_sequence(preds, frames, include_ground=True)
    assert r["num_points"] == 5
    with pytest.raises(ValueError, match="frame 1"):
        evaluate_sequence([preds[0], np.zeros((3, 3))], frames)
    with pytest.raises(ValueError, match="1 predicted frames"):
        evaluate_sequence(preds[:1], frames)


def test_evaluate_simulated_perfect_and_zero():
    from floxels_ext.evaluation.sim import simulate_sequence

    seq = simulate_sequence("urban", 2, seed=2, small=True)
    perfect = evaluate_sequence([f.flow for f in seq], seq.frames)
    assert perfect["dynamic_epe"] == 0 and perfect["dynamic_acc5"] == 1 and perfect["mean_dynamic_normalized_epe"] == 0
    assert perfect["dynamic_angle"] == 0 and perfect["dynamic_angle_count"] == perfect["dynamic_count"]
    zero = evaluate_sequence([np.zeros_like(f.flow) for f in seq], seq.frames)
    assert zero["mean_dynamic_normalized_epe"] == pytest.approx(1.0)
    assert math.isnan(zero["dynamic_angle"]) and zero["dynamic_angle_count"] == 0
    assert zero["static_epe"] == 0 and zero["dynamic_acc5"] == 0
