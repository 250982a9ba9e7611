"""Scene-flow metrics: EPE / Acc5 / Acc10 / outliers / angle, three-way EPE, and the
Argoverse 2 (2024) bucketed normalized EPE.

Conventions (all flows in metres per frame):

* EPE = ||pred - gt||. Relative error = EPE / ||gt||; the relative criteria only apply to
  points with ||gt|| > 1e-6 (a relative error to a zero vector is undefined), so for a static
  point Acc5/Acc10 use the absolute threshold alone and "outlier" means EPE > 0.3 m.
* Acc5: EPE < 0.05 m or relative < 5 %. Acc10: EPE < 0.1 m or relative < 10 %.
  Outliers: EPE > 0.3 m or relative > 10 %.
* Angle error: the angle in RADIANS between the predicted and ground-truth 3D flow vectors,
  ``atan2(||p x g||, p . g)``. A zero vector has no direction: if exactly one of the two
  vectors is (near) zero the angle is pi/2, if both are, 0. It is informative for dynamic
  points; for static ones it mostly measures whether the prediction is exactly zero.
* Dynamic points: ||gt|| > 0.05 m per frame (or a given mask). Averages are point-weighted:
  frames are concatenated, not averaged per frame.
* An empty subset gives NaN (``None`` in JSON).
"""

from __future__ import annotations

import math
from typing import Sequence as _Seq

import numpy as np

__all__ = [
    "DYNAMIC_THRESHOLD",
    "CLASS_NAMES",
    "endpoint_errors",
    "angle_errors",
    "flow_metrics",
    "threeway_epe",
    "BucketedEPE",
    "bucketed_epe",
    "evaluate_sequence",
]

DYNAMIC_THRESHOLD = 0.05
CLASS_NAMES = ("background", "car", "other_vehicle", "pedestrian", "wheeled_vru")
_ZERO = 1e-6


def _as_flow(a, name: str) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {a.shape}")
    return a


def _check_pair(pred, gt):
    pred, gt = _as_flow(pred, "pred"), _as_flow(gt, "gt")
    if pred.shape != gt.shape:
        raise ValueError(f"pred has {pred.shape[0]} points but gt has {gt.shape[0]}")
    return pred, gt


def endpoint_errors(pred, gt) -> np.ndarray:
    pred, gt = _check_pair(pred, gt)
    return np.linalg.norm(pred - gt, axis=1)


def angle_errors(pred, gt) -> np.ndarray:
    """Per-point angle (radians) between pred and gt; see the module docstring for zeros."""
    pred, gt = _check_pair(pred, gt)
    cross = np.linalg.norm(np.cross(pred, gt), axis=1)
    dot = np.einsum("ij,ij->i", pred, gt)
    ang = np.arctan2(cross, dot)
    pz = np.linalg.norm(pred, axis=1) <= _ZERO
    gz = np.linalg.norm(gt, axis=1) <= _ZERO
    ang[pz ^ gz] = math.pi / 2
    ang[pz & gz] = 0.0
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
        "angle": _mean(ang),
        "count": int(epe.size),
    }


def flow_metrics(pred, gt, dynamic_mask=None, valid_mask=None) -> dict[str, float]:
    """EPE, Acc5, Acc10, outliers and angle error for all, dynamic and static points.

    Keys: ``{all,dynamic,static}_{epe,acc5,acc10,outliers,angle,count}``. ``dynamic_mask``
    defaults to ||gt|| > 0.05; ``valid_mask`` restricts evaluation to a subset of points.
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
    """Three-way EPE: foreground dynamic, foreground static, background, and their mean.

    Foreground = class != 0. The mean is over the non-empty groups (NaN if all are empty).
    """
    pred, gt = _check_pair(pred, gt)
    classes = np.asarray(classes)
    if classes.shape != (gt.shape[0],):
        raise ValueError(f"classes has shape {classes.shape}, expected ({gt.shape[0]},)")
    dyn = np.linalg.norm(gt, axis=1) > DYNAMIC_THRESHOLD if dynamic_mask is None else np.asarray(dynamic_mask, bool)
    epe = np.linalg.norm(pred - gt, axis=1)
    fg = classes != 0
    parts = {
        "foreground_dynamic": _mean(epe[fg & dyn]),
        "foreground_static": _mean(epe[fg & ~dyn]),
        "background": _mean(epe[~fg]),
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
        if classes.size and (classes.min() < 0 or classes.max() >= self.num_classes):
            raise ValueError(f"classes must be in 0..{self.num_classes - 1}")
        if valid_mask is not None:
            m = np.asarray(valid_mask, dtype=bool)
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


def evaluate_sequence(preds: _Seq, frames: _Seq, include_ground: bool = False) -> dict:
    """All metrics over a sequence. ``preds``: per-frame (N, 3) flows (or objects with ``flow``);
    ``frames``: ground-truth frames with ``flow`` and optionally ``classes``, ``dynamic``, ``ground``.

    Missing ``classes`` means background, missing ``dynamic`` is derived from ||gt|| > 0.05.
    Ground points are excluded unless ``include_ground`` (as in the AV2 protocol: ground flow is
    trivially zero and would dominate the static numbers).

    Returns the JSON keys ``dynamic_{epe,acc5,acc10,angle}``, ``static_{epe,acc5,acc10}``,
    ``threeway_epe`` (dict), ``dynamic_normalized_epe`` (per class), ``mean_dynamic_normalized_epe``,
    ``mean_static_epe``, plus ``static_angle``, ``{dynamic,static}_outliers``, counts,
    ``static_epe_per_class`` and ``num_frames`` / ``num_points``.
    """
    if len(preds) != len(frames):
        raise ValueError(f"got {len(preds)} predicted frames for {len(frames)} ground-truth frames")
    P, G, C, D, V = [], [], [], [], []
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
        d = _get(f, "dynamic")
        gr = _get(f, "ground")
        P.append(p)
        G.append(g)
        C.append(np.zeros(n, np.int64) if c is None else np.asarray(c, np.int64))
        D.append(np.linalg.norm(g, axis=1) > DYNAMIC_THRESHOLD if d is None else np.asarray(d, bool))
        V.append(np.ones(n, bool) if include_ground or gr is None else ~np.asarray(gr, bool))
    cat = lambda xs, shape: np.concatenate(xs) if xs else np.zeros(shape)  # noqa: E731
    p, g = cat(P, (0, 3)), cat(G, (0, 3))
    c, d, v = cat(C, (0,)).astype(np.int64), cat(D, (0,)).astype(bool), cat(V, (0,)).astype(bool)

    fm = flow_metrics(p, g, d, v)
    tw = threeway_epe(p[v], g[v], c[v], d[v])
    bk = BucketedEPE().update(p, g, c, v).compute()
    out = {k: fm[k] for k in (
        "dynamic_epe", "dynamic_acc5", "dynamic_acc10", "dynamic_angle", "dynamic_outliers", "dynamic_count",
        "static_epe", "static_acc5", "static_acc10", "static_angle", "static_outliers", "static_count",
    )}
    out["threeway_epe"] = tw
    out["dynamic_normalized_epe"] = bk["dynamic_normalized_epe"]
    out["mean_dynamic_normalized_epe"] = bk["mean_dynamic_normalized_epe"]
    out["static_epe_per_class"] = bk["static_epe"]
    out["mean_static_epe"] = bk["mean_static_epe"]
    out["num_frames"] = len(frames)
    out["num_points"] = int(v.sum())
    return out
