"""What ``bench/compare.py`` and its ``--merge`` (``compare_merge.py``) share: the metrics of
row records over their frames, and the JSON-safe copy and log line they write. Its own module
so that neither of the two imports the other at load time."""

from __future__ import annotations

import math

import numpy as np

from floxels_ext.evaluation.metrics import evaluate_sequence
from floxels_ext.evaluation.protocol import META_CLASSES

__all__ = ["log", "evaluate_rows", "car_speed_ratio", "clean"]


def log(msg: str) -> None:
    print(msg, flush=True)


def evaluate_rows(records, preds_of, truth_of):
    """Metrics of each row record over every (scene, frame) it has predictions for."""
    for r in records:
        P, G = [], []
        for scene, frames in r["frames"].items():
            for f in frames:
                P.append(preds_of(r["key"], scene, f))
                G.append(truth_of(scene, f))
        r["metrics"] = evaluate_sequence(P, G)
        r["metrics"]["car_speed_ratio"] = car_speed_ratio(P, G)
        n = sum(len(v) for v in r["frames"].values())
        r["seconds_per_frame"] = sum(r["seconds"].values()) / max(n, 1)
    return records


def car_speed_ratio(preds, truths) -> float:
    """Median predicted / true speed over the evaluated dynamic car points (issue 33's
    measure of speed shrinkage); NaN without any."""
    r = []
    for p, t in zip(preds, truths):
        keep = t["dynamic"] & (np.asarray(t["classes"]) == META_CLASSES.index("car"))
        if "ground" in t:
            keep &= ~np.asarray(t["ground"], bool)
        true = np.linalg.norm(t["flow"][keep], axis=1)
        ok = true > 1e-6
        r.append(np.linalg.norm(np.asarray(p, np.float64)[keep][ok], axis=1) / true[ok])
    r = np.concatenate(r) if r else np.zeros(0)
    return float(np.median(r)) if r.size else float("nan")


def clean(o):
    """JSON-safe copy: NaN -> None (strict JSON has no NaN), tuples -> lists."""
    if isinstance(o, float):
        return None if math.isnan(o) else o
    if isinstance(o, dict):
        return {str(k): clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [clean(v) for v in o]
    return o
