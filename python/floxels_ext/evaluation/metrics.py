"""Scene-flow metrics: EPE / Acc5 / Acc10 / outliers / angle, three-way EPE, and the
Argoverse 2 (2024) bucketed normalized EPE, conformant with the official evaluation
(``bucketed-scene-flow-eval``; cross-checked in tests/evaluation/test_metrics_av2.py).

Conventions (all flows in metres per frame):

* EPE = ||pred - gt||. Relative error = EPE / ||gt||; the relative criteria only apply to
  points with ||gt|| > 1e-6 (a relative error to a zero vector is undefined), so for a static
  point Acc5/Acc10 use the absolute threshold alone and "outlier" means EPE > 0.3 m.
* Acc5: EPE < 0.05 m or relative < 5 %. Acc10: EPE < 0.1 m or relative < 10 %.
  Outliers: EPE > 0.3 m or relative > 10 %.
* Angle error: the angle in RADIANS between the predicted and ground-truth 3D flow vectors,
  ``atan2(||p x g||, p . g)``, defined ONLY where both ||gt|| and ||pred|| exceed
  ``ANGLE_MIN_NORM`` (0.05 m per frame, the dynamic threshold): a (near) zero vector has no
  direction, and the direction of a motion below the noise level is noise. Elsewhere
  ``angle_errors`` gives NaN; the averages are over the defined points and ``*_angle_count``
  says how many there were. So static points (||gt|| <= 0.05) have no angle error at all
  (``static_angle`` is NaN), and a prediction of zero flow has none either.
* Dynamic points: ||gt|| > 0.05 m per frame (or a given mask). Averages are point-weighted:
  frames are concatenated, not averaged per frame.
* Predictions must be finite: NaN or inf raises ``ValueError`` (a NaN would otherwise vanish
  from a class's bucket averages and silently drop that class from the means).
* Classes: the meta-classes ``CLASS_NAMES`` (0 background .. 4 wheeled VRU); ``IGNORE`` (-1)
  marks points that no metric counts. ``evaluate_sequence(..., category_map="av2")`` maps
  Argoverse 2 label classes to them as the official evaluation does (``protocol.py``), and
  ``eval_box=35.0`` keeps only points with max(|x|, |y|) < 35 m in the scan's frame.
* An empty subset gives NaN (``None`` in JSON).
"""

from __future__ import annotations

import math
from typing import Sequence as _Seq

import numpy as np

from floxels_ext.evaluation.protocol import IGNORE, META_CLASSES, eval_box_mask, map_categories, resolve_category_map

__all__ = [
    "DYNAMIC_THRESHOLD",
    "ANGLE_MIN_NORM",
    "CLASS_NAMES",
    "IGNORE",
    "endpoint_errors",
    "angle_errors",
    "flow_metrics",
    "threeway_epe",
    "BucketedEPE",
    "bucketed_epe",
    "evaluate_sequence",
]

DYNAMIC_THRESHOLD = 0.05
ANGLE_MIN_NORM = 0.05  # metres per frame: both vectors must be longer for an angle error
CLASS_NAMES = META_CLASSES
_ZERO = 1e-6


def _as_flow(a, name: str) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {a.shape}")
    bad = ~np.isfinite(a).all(axis=1)
    if bad.any():
        raise ValueError(f"{name} has {int(bad.sum())} non-finite (NaN/inf) vector(s) of {a.shape[0]} "
                         f"(first at point {int(np.argmax(bad))}); metrics need finite flow for every point")
    return a


def _check_pair(pred, gt):
    pred, gt = _as_flow(pred, "pred"), _as_flow(gt, "gt")
    if pred.shape != gt.shape:
        raise ValueError(f"pred has {pred.shape[0]} points but gt has {gt.shape[0]}")
    return pred, gt


def endpoint_errors(pred, gt) -> np.ndarray:
    pred, gt = _check_pair(pred, gt)
    return np.linalg.norm(pred - gt, axis=1)


def angle_errors(pred, gt, min_norm: float = ANGLE_MIN_NORM) -> np.ndarray:
    """Per-point angle (radians) between pred and gt; NaN where ||pred|| or ||gt|| <= ``min_norm``
    (the angle is undefined there; see the module docstring)."""
    pred, gt = _check_pair(pred, gt)
    cross = np.linalg.norm(np.cross(pred, gt), axis=1)
    dot = np.einsum("ij,ij->i", pred, gt)
    ang = np.arctan2(cross, dot)
    defined = (np.linalg.norm(pred, axis=1) > min_norm) & (np.linalg.norm(gt, axis=1) > min_norm)
    ang[~defined] = np.nan
    return ang


def _mean(x: np.ndarray) -> float:
    return float(x.mean()) if x.size else float("nan")


def _subset_metrics(epe, gt_norm, ang) -> dict[str, float]:
    has_rel = gt_norm > _ZERO
    rel = np.divide(epe, gt_norm, out=np.full_like(epe, np.inf), where=has_rel)
    rel_ok = lambda thr: has_rel & (rel < thr)  # noqa: E731
    return {
        "epe": _mean(epe),
        "acc5": _mean(((epe < 0.05) | rel_ok(0.05)).astype(np.float64)),
        "acc10": _mean(((epe < 0.1) | rel_ok(0.1)).astype(np.float64)),
        "outliers": _mean(((epe > 0.3) | (has_rel & (rel > 0.1))).astype(np.float64)),
        "angle": _mean(ang[~np.isnan(ang)]),
        "angle_count": int((~np.isnan(ang)).sum()),
        "count": int(epe.size),
    }


def flow_metrics(pred, gt, dynamic_mask=None, valid_mask=None) -> dict[str, float]:
    """EPE, Acc5, Acc10, outliers and angle error for all, dynamic and static points.

    Keys: ``{all,dynamic,static}_{epe,acc5,acc10,outliers,angle,angle_count,count}``;
    ``angle`` averages only the points where it is defined (``angle_count`` of them).
    ``dynamic_mask`` defaults to ||gt|| > 0.05; ``valid_mask`` restricts evaluation to a subset.
    """
    pred, gt = _check_pair(pred, gt)
    gt_norm = np.linalg.norm(gt, axis=1)
    dyn = gt_norm > DYNAMIC_THRESHOLD if dynamic_mask is None else np.asarray(dynamic_mask, dtype=bool)
    if dyn.shape != gt_norm.shape:
        raise ValueError(f"dynamic_mask has shape {dyn.shape}, expected ({gt.shape[0]},)")
    valid = np.ones_like(dyn) if valid_mask is None else np.asarray(valid_mask, dtype=bool)
    epe = np.linalg.norm(pred - gt, axis=1)
    ang = angle_errors(pred, gt)
    out: dict[str, float] = {}
    for name, m in (("all", valid), ("dynamic", valid & dyn), ("static", valid & ~dyn)):
        for k, v in _subset_metrics(epe[m], gt_norm[m], ang[m]).items():
            out[f"{name}_{k}"] = v
    return out


def threeway_epe(pred, gt, classes, dynamic_mask=None) -> dict[str, float]:
    """Three-way EPE: foreground dynamic, foreground static, static background, and their mean.

    Foreground = class > 0; class ``IGNORE`` (-1) counts nowhere. Background is scored on its
    static points, as the official ``ThreeWayEPEEvaluator`` does (its BACKGROUND static bucket).
    The mean is over the non-empty groups (NaN if all are empty).
    """
    pred, gt = _check_pair(pred, gt)
    classes = np.asarray(classes)
    if classes.shape != (gt.shape[0],):
        raise ValueError(f"classes has shape {classes.shape}, expected ({gt.shape[0]},)")
    dyn = np.linalg.norm(gt, axis=1) > DYNAMIC_THRESHOLD if dynamic_mask is None else np.asarray(dynamic_mask, bool)
    epe = np.linalg.norm(pred - gt, axis=1)
    fg = classes > 0
    parts = {
        "foreground_dynamic": _mean(epe[fg & dyn]),
        "foreground_static": _mean(epe[fg & ~dyn]),
        "background": _mean(epe[(classes == 0) & ~dyn]),
    }
    vals = [v for v in parts.values() if not math.isnan(v)]
    parts["mean"] = float(np.mean(vals)) if vals else float("nan")
    return parts


class BucketedEPE:
    """Argoverse 2 (2024) bucketed scene-flow metric, accumulated over frames.

    Points are binned by ground-truth speed (||gt|| per frame) into buckets of width 0.04 from
    0 to 2.0 plus one bucket [2.0, inf); bucket 0 is "static". Per meta-class and bucket we
    accumulate the EPE sum, speed sum and count (point-weighted over all frames). Then per class:

    * static EPE = mean EPE in bucket 0;
    * dynamic normalized EPE = unweighted mean, over the non-empty moving buckets, of
      (mean EPE / mean speed) of that bucket; NaN if the class has no moving points.

    ``mean_dynamic_normalized_epe`` / ``mean_static_epe`` average the classes that have a value.
    Points of class ``IGNORE`` (-1) are skipped. This is the official ``BucketedEPEEvaluator``'s
    computation (51 edges ``linspace(0, 2, 51)`` plus [2, inf), meta-classes merged point-weighted).
    """

    def __init__(self, num_classes: int = len(CLASS_NAMES), bucket_width: float = 0.04, max_speed: float = 2.0):
        self.num_classes = num_classes
        # edges [0, 0.04, ..., 2.0]; values >= 2.0 fall in the extra last bucket
        self.edges = np.linspace(0.0, max_speed, int(round(max_speed / bucket_width)) + 1)
        nb = len(self.edges)  # (len(edges) - 1) regular buckets + 1 overflow bucket
        self.epe_sum = np.zeros((num_classes, nb))
        self.speed_sum = np.zeros((num_classes, nb))
        self.count = np.zeros((num_classes, nb), dtype=np.int64)

    def update(self, pred, gt, classes, valid_mask=None) -> "BucketedEPE":
        pred, gt = _check_pair(pred, gt)
        classes = np.asarray(classes).astype(np.int64)
        if classes.shape != (gt.shape[0],):
            raise ValueError(f"classes has shape {classes.shape}, expected ({gt.shape[0]},)")
        if classes.size and (classes.min() < IGNORE or classes.max() >= self.num_classes):
            raise ValueError(f"classes must be in 0..{self.num_classes - 1} (or {IGNORE} to ignore a point)")
        m = classes != IGNORE
        if valid_mask is not None:
            m &= np.asarray(valid_mask, dtype=bool)
        pred, gt, classes = pred[m], gt[m], classes[m]
        speed = np.linalg.norm(gt, axis=1)
        epe = np.linalg.norm(pred - gt, axis=1)
        bucket = np.searchsorted(self.edges, speed, side="right") - 1  # [e_i, e_i+1) -> i; >= 2.0 -> last
        flat = classes * self.count.shape[1] + bucket
        size = self.count.size
        self.epe_sum += np.bincount(flat, epe, size).reshape(self.count.shape)
        self.speed_sum += np.bincount(flat, speed, size).reshape(self.count.shape)
        self.count += np.bincount(flat, minlength=size).reshape(self.count.shape)
        return self

    def compute(self) -> dict:
        with np.errstate(invalid="ignore", divide="ignore"):
            mean_epe = self.epe_sum / self.count
            mean_speed = self.speed_sum / self.count
        static, dynamic = {}, {}
        for c in range(self.num_classes):
            name = CLASS_NAMES[c] if c < len(CLASS_NAMES) else str(c)
            static[name] = float(mean_epe[c, 0]) if self.count[c, 0] else float("nan")
            moving = self.count[c, 1:] > 0
            ratio = mean_epe[c, 1:][moving] / mean_speed[c, 1:][moving]
            dynamic[name] = float(np.mean(ratio)) if moving.any() else float("nan")
        return {
            "static_epe": static,
            "dynamic_normalized_epe": dynamic,
            "mean_static_epe": _nanmean(static.values()),
            "mean_dynamic_normalized_epe": _nanmean(dynamic.values()),
        }


def _nanmean(vals) -> float:
    vals = [v for v in vals if not math.isnan(v)]
    return float(np.mean(vals)) if vals else float("nan")


def bucketed_epe(preds, gts, classes, valid_masks=None) -> dict:
    """Bucketed metric over lists of per-frame arrays (see ``BucketedEPE``)."""
    acc = BucketedEPE()
    masks = valid_masks if valid_masks is not None else [None] * len(preds)
    for p, g, c, m in zip(preds, gts, classes, masks, strict=True):
        acc.update(p, g, c, m)
    return acc.compute()


def _get(frame, key):
    return frame.get(key) if isinstance(frame, dict) else getattr(frame, key, None)


def evaluate_sequence(preds: _Seq, frames: _Seq, include_ground: bool = False, *, category_map=None,
                      eval_box: float | None = None) -> dict:
    """All metrics over a sequence. ``preds``: per-frame (N, 3) flows (or objects with ``flow``);
    ``frames``: ground-truth frames with ``flow`` and optionally ``classes``, ``dynamic``, ``ground``,
    ``points`` and ``pose``.

    Missing ``classes`` means background, missing ``dynamic`` is derived from ||gt|| > 0.05.
    Ground points are excluded unless ``include_ground`` (as in the AV2 protocol: ground flow is
    trivially zero and would dominate the static numbers).

    ``category_map``: None when ``classes`` already hold meta-class ids (0..4, as the simulator
    writes them); ``"av2"`` for Argoverse 2 label classes (``protocol.AV2_CATEGORY_MAP``: the
    official evaluation's meta-classes, its ignored categories left out of every metric); or a
    mapping ``{class id: meta-class name/index, or None to ignore}``. A class id missing from
    the map raises ``ValueError``.

    ``eval_box``: None scores all points; a half size in metres (35.0 for the official AV2
    evaluation, ``protocol.AV2_EVAL_BOX``) keeps the points with max(|x|, |y|) < eval_box in the
    frame's own coordinates (world points are brought back with the frame's ``pose``).

    Raises ``ValueError`` naming the frame for a non-finite prediction or ground truth.

    Returns the JSON keys ``dynamic_{epe,acc5,acc10,angle}``, ``static_{epe,acc5,acc10}``,
    ``threeway_epe`` (dict), ``dynamic_normalized_epe`` (per class), ``mean_dynamic_normalized_epe``,
    ``mean_static_epe``, plus ``static_angle``, ``{dynamic,static}_angle_count``,
    ``{dynamic,static}_outliers``, counts, ``static_epe_per_class``, ``num_frames`` /
    ``num_points`` (scored points), ``ignored_count`` (ignored categories), ``outside_box_count``,
    ``eval_box`` and ``category_map`` (None, "av2" or "custom").
    """
    if len(preds) != len(frames):
        raise ValueError(f"got {len(preds)} predicted frames for {len(frames)} ground-truth frames")
    cmap = resolve_category_map(category_map)
    if eval_box is not None and not (eval_box > 0):
        raise ValueError(f"eval_box must be a positive half size in metres or None, got {eval_box}")
    P, G, C, D, V = [], [], [], [], []
    ignored = outside = 0
    for i, (p, f) in enumerate(zip(preds, frames)):
        p = _get(p, "flow") if not isinstance(p, np.ndarray) and _get(p, "flow") is not None else p
        g = _get(f, "flow")
        if g is None:
            raise ValueError(f"ground-truth frame {i} has no flow")
        g = _as_flow(g, f"ground-truth flow of frame {i}")
        p = _as_flow(p, f"predicted flow of frame {i}")
        if p.shape != g.shape:
            raise ValueError(f"frame {i}: prediction has {p.shape[0]} points, ground truth {g.shape[0]}")
        n = g.shape[0]
        c = _get(f, "classes")
        c = np.zeros(n, np.int64) if c is None else np.asarray(c).astype(np.int64)
        if c.shape != (n,):
            raise ValueError(f"frame {i}: classes has shape {c.shape}, expected ({n},)")
        if cmap is not None:
            c = map_categories(c, cmap, f"classes of frame {i}")
        elif n and (c.min() < IGNORE or c.max() >= len(CLASS_NAMES)):
            raise ValueError(f"frame {i}: classes must be meta-class ids 0..{len(CLASS_NAMES) - 1} "
                             f"(or {IGNORE}); pass category_map for dataset categories")
        d = _get(f, "dynamic")
        gr = _get(f, "ground")
        v = np.ones(n, bool) if include_ground or gr is None else ~np.asarray(gr, bool)
        ign = v & (c == IGNORE)
        ignored += int(ign.sum())
        v &= ~ign
        if eval_box is not None:
            pts = _get(f, "points")
            if pts is None:
                raise ValueError(f"frame {i} has no points: eval_box needs them")
            inside = eval_box_mask(pts, _get(f, "pose"), eval_box)
            outside += int((v & ~inside).sum())
            v &= inside
        P.append(p)
        G.append(g)
        C.append(c)
        D.append(np.linalg.norm(g, axis=1) > DYNAMIC_THRESHOLD if d is None else np.asarray(d, bool))
        V.append(v)
    cat = lambda xs, shape: np.concatenate(xs) if xs else np.zeros(shape)  # noqa: E731
    p, g = cat(P, (0, 3)), cat(G, (0, 3))
    c, d, v = cat(C, (0,)).astype(np.int64), cat(D, (0,)).astype(bool), cat(V, (0,)).astype(bool)

    fm = flow_metrics(p, g, d, v)
    tw = threeway_epe(p[v], g[v], c[v], d[v])
    bk = BucketedEPE().update(p, g, c, v).compute()
    out = {k: fm[k] for k in (
        "dynamic_epe", "dynamic_acc5", "dynamic_acc10", "dynamic_angle", "dynamic_angle_count", "dynamic_outliers",
        "dynamic_count", "static_epe", "static_acc5", "static_acc10", "static_angle", "static_angle_count",
        "static_outliers", "static_count",
    )}
    out["threeway_epe"] = tw
    out["dynamic_normalized_epe"] = bk["dynamic_normalized_epe"]
    out["mean_dynamic_normalized_epe"] = bk["mean_dynamic_normalized_epe"]
    out["static_epe_per_class"] = bk["static_epe"]
    out["mean_static_epe"] = bk["mean_static_epe"]
    out["num_frames"] = len(frames)
    out["num_points"] = int(v.sum())
    out["ignored_count"] = ignored
    out["outside_box_count"] = outside
    out["eval_box"] = None if eval_box is None else float(eval_box)
    out["category_map"] = None if cmap is None else ("av2" if isinstance(category_map, str) else "custom")
    return out
