"""The paper's evaluation protocol cropping (appendix: drop points within 3 m of the sensor,
beyond 50 m, higher than 4 m, and ground points)."""

from __future__ import annotations

import numpy as np


def protocol_mask(points: np.ndarray, sensor_position: np.ndarray, *, min_range: float = 3.0,
                  max_range: float = 50.0, max_height: float = 4.0, ground: np.ndarray | None = None,
                  sensor_height: float = 1.8) -> np.ndarray:
    """Boolean mask of the points the protocol keeps.

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
