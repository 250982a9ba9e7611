"""Evaluation protocols: the paper's cropping, and the Argoverse 2 (2024) category map and
35 m evaluation box of the official bucketed scene-flow evaluation.

* ``protocol_mask``: the paper's appendix cropping (drop points within 3 m of the sensor, beyond
  50 m, higher than 4 m, and ground points).
* ``AV2_CATEGORIES``: the Argoverse 2 scene-flow label classes, indexed by the label's class id
  (av2-api convention: 0 = no object / background, 1 = ANIMAL, ... 30 = WHEELED_RIDER).
* ``AV2_META_CLASSES`` / ``AV2_CATEGORY_MAP``: how the official evaluation
  (``bucketed-scene-flow-eval``, ``BUCKETED_METACATAGORIES``) merges them into the five
  meta-classes of ``metrics.CLASS_NAMES``. ``AV2_IGNORED`` are the categories it leaves out
  (road signs and animals: labelling oddities such as moving stop signs on school buses);
  their points count in no metric.
* ``eval_box_mask``: the official evaluation scores only points whose ego-frame x and y both lie
  within 35 m (``max(|x|, |y|) < 35``, in the frame of the scan the flow starts from).
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

__all__ = [
    "protocol_mask",
    "META_CLASSES",
    "IGNORE",
    "AV2_CATEGORIES",
    "AV2_META_CLASSES",
    "AV2_IGNORED",
    "AV2_CATEGORY_MAP",
    "AV2_EVAL_BOX",
    "resolve_category_map",
    "map_categories",
    "eval_box_mask",
]

# the meta-classes every class-based metric reports (index = class id in simulator/seqio frames)
META_CLASSES = ("background", "car", "other_vehicle", "pedestrian", "wheeled_vru")
IGNORE = -1  # meta-class id of points that no metric counts

AV2_CATEGORIES = (
    "BACKGROUND", "ANIMAL", "ARTICULATED_BUS", "BICYCLE", "BICYCLIST", "BOLLARD", "BOX_TRUCK", "BUS",
    "CONSTRUCTION_BARREL", "CONSTRUCTION_CONE", "DOG", "LARGE_VEHICLE", "MESSAGE_BOARD_TRAILER",
    "MOBILE_PEDESTRIAN_CROSSING_SIGN", "MOTORCYCLE", "MOTORCYCLIST", "OFFICIAL_SIGNALER", "PEDESTRIAN",
    "RAILED_VEHICLE", "REGULAR_VEHICLE", "SCHOOL_BUS", "SIGN", "STOP_SIGN", "STROLLER",
    "TRAFFIC_LIGHT_TRAILER", "TRUCK", "TRUCK_CAB", "VEHICULAR_TRAILER", "WHEELCHAIR", "WHEELED_DEVICE",
    "WHEELED_RIDER",
)
AV2_META_CLASSES = {
    "background": ("BACKGROUND",),
    "car": ("REGULAR_VEHICLE",),
    "other_vehicle": ("BOX_TRUCK", "LARGE_VEHICLE", "RAILED_VEHICLE", "TRUCK", "TRUCK_CAB", "VEHICULAR_TRAILER",
                      "ARTICULATED_BUS", "BUS", "SCHOOL_BUS"),
    "pedestrian": ("PEDESTRIAN", "STROLLER", "WHEELCHAIR", "OFFICIAL_SIGNALER"),
    "wheeled_vru": ("BICYCLE", "BICYCLIST", "MOTORCYCLE", "MOTORCYCLIST", "WHEELED_DEVICE", "WHEELED_RIDER"),
}
AV2_IGNORED = ("ANIMAL", "DOG", "BOLLARD", "CONSTRUCTION_BARREL", "CONSTRUCTION_CONE",
               "MOBILE_PEDESTRIAN_CROSSING_SIGN", "SIGN", "STOP_SIGN", "MESSAGE_BOARD_TRAILER",
               "TRAFFIC_LIGHT_TRAILER")
_META_OF = {c: META_CLASSES.index(m) for m, cats in AV2_META_CLASSES.items() for c in cats}
# AV2 label class id -> meta-class index (IGNORE for the categories the official evaluation skips)
AV2_CATEGORY_MAP: dict[int, int] = {i: _META_OF.get(name, IGNORE) for i, name in enumerate(AV2_CATEGORIES)}
AV2_EVAL_BOX = 35.0  # metres: half size of the official evaluation box


def protocol_mask(points: np.ndarray, sensor_position: np.ndarray, *, min_range: float = 3.0,
                  max_range: float = 50.0, max_height: float = 4.0, ground: np.ndarray | None = None,
                  sensor_height: float = 1.8) -> np.ndarray:
    """Boolean mask of the points the paper's protocol keeps.

    Range is the horizontal distance to the sensor; height is measured from the ground level
    under the sensor (sensor z minus ``sensor_height``). ``ground`` (bool per point), when
    given, removes ground points.
    """
    p = np.asarray(points)
    s = np.asarray(sensor_position, dtype=np.float64).reshape(3)
    r = np.hypot(p[:, 0] - s[0], p[:, 1] - s[1])
    keep = (r >= min_range) & (r <= max_range) & (p[:, 2] - (s[2] - sensor_height) <= max_height)
    if ground is not None:
        keep &= ~np.asarray(ground, dtype=bool)
    return keep


def resolve_category_map(category_map) -> dict[int, int] | None:
    """Normalise a category map: None (classes already are meta-class ids), ``"av2"``, or a
    mapping ``{category id: meta-class name, index, or None to ignore}``."""
    if category_map is None:
        return None
    if isinstance(category_map, str):
        if category_map.lower() != "av2":
            raise ValueError(f"unknown category map {category_map!r}; use 'av2' or a mapping")
        return dict(AV2_CATEGORY_MAP)
    if not isinstance(category_map, Mapping):
        raise TypeError(f"category_map must be None, 'av2' or a mapping, got {type(category_map).__name__}")
    out = {}
    for k, v in category_map.items():
        try:
            key = int(k)
        except (TypeError, ValueError):
            raise ValueError(f"category map key {k!r} is not an integer class id") from None
        if v is None or (isinstance(v, str) and v.lower() in ("ignore", "ignored")):
            out[key] = IGNORE
        elif isinstance(v, str):
            if v.lower() not in META_CLASSES:
                raise ValueError(f"category map: {k} -> {v!r} is not a meta-class; choose from {META_CLASSES} "
                                 f"or null to ignore")
            out[key] = META_CLASSES.index(v.lower())
        elif isinstance(v, (int, np.integer)) and (v == IGNORE or 0 <= v < len(META_CLASSES)):
            out[key] = int(v)
        else:
            raise ValueError(f"category map: {k} -> {v!r} is not a meta-class name or index 0..{len(META_CLASSES) - 1}")
    return out


def map_categories(classes: np.ndarray, category_map: dict[int, int], where: str = "classes") -> np.ndarray:
    """Meta-class id (or ``IGNORE``) of each point; an id missing from the map is an error."""
    c = np.asarray(classes).astype(np.int64)
    ids, inv = np.unique(c, return_inverse=True)
    unknown = [int(i) for i in ids if int(i) not in category_map]
    if unknown:
        raise ValueError(f"{where}: class id(s) {unknown} are not in the category map (known: "
                         f"{min(category_map)}..{max(category_map)})" if category_map else f"{where}: empty category map")
    return np.array([category_map[int(i)] for i in ids], dtype=np.int64)[inv].reshape(c.shape)


def eval_box_mask(points: np.ndarray, pose: np.ndarray | None = None, half_size: float = AV2_EVAL_BOX) -> np.ndarray:
    """Points inside the official evaluation box: ``max(|x|, |y|) < half_size`` in the scan's own
    (ego) frame. ``pose`` (4x4, scan frame -> the points' frame) brings world-frame points back
    into the scan's frame; without it the points are taken to be in the scan's frame already."""
    p = np.asarray(points, dtype=np.float64)
    if pose is not None:
        T = np.asarray(pose, dtype=np.float64)
        p = (p - T[:3, 3]) @ T[:3, :3]
    return np.maximum(np.abs(p[:, 0]), np.abs(p[:, 1])) < half_size
