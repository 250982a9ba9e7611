"""What the numpy reference, the compiled op and the torch path of the scan preprocessing share:
the per-point classes, the settings (:class:`Preprocess`) and the ground grid's limits.

Its own module so that ``masks`` (numpy, and the dispatch to the op or the GPU) and
``masks_torch`` (the GPU path) both import it and neither imports the other at load time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["CROPPED", "KEPT", "GROUND", "OUTLIER", "MAX_GROUND_CELLS", "Preprocess"]


# Per-point classes of :func:`~floxels_ext.lidar.preprocess.masks.preprocess_classes` (uint8): dropped by the
# range/height crop or non-finite, kept (optimised), removed as ground, removed as an outlier (step 0 of
# the ground removal, masks' module doc).
CROPPED, KEPT, GROUND, OUTLIER = 0, 1, 2, 3


# The ground grid covers at most this many cells (+-500 m at 0.5 m): the grid, not the points'
# extent, bounds the memory, so a stray point kilometres away costs nothing.
MAX_GROUND_CELLS = 2001 * 2001


def _window_cells(window: float, cell_size: float) -> int:
    return max(1, int(round(window / cell_size)) | 1)  # odd, so the window is centred


def _check_ground_args(cell_size, window, max_distance) -> None:
    if not (cell_size > 0 and window > 0):
        raise ValueError(f"cell_size and window must be > 0, got {cell_size}, {window}")
    if max_distance is not None and not (np.isfinite(max_distance) and max_distance > 0):
        raise ValueError(f"max_distance must be a finite number > 0 (or None), got {max_distance}")
    if max_distance is not None and (2 * max_distance / cell_size + 1) ** 2 > MAX_GROUND_CELLS:
        raise ValueError(f"a ground grid of {cell_size} m cells over +-{max_distance} m would have more than "
                         f"{MAX_GROUND_CELLS:,} cells; lower max_distance or raise cell_size")


@dataclass(frozen=True)
class Preprocess:
    """Per-scan preprocessing settings (the paper's protocol by default)."""

    min_range: float | None = 3.0       # m, horizontal distance to the sensor
    max_range: float | None = 50.0
    max_height: float | None = 4.0      # m above the local ground surface
    remove_ground: bool = True
    ground_cell: float = 0.5            # m, grid cell of the lowest-point map
    ground_window: float = 8.0          # m, opening window (wider than the largest object)
    ground_threshold: float = 0.3       # m above the ground surface still counted as ground
    ground_max_rise: float | None = 0.5  # m the surface may rise above the fitted plane (None: no cap)
    # m: without max_range, only points this close (horizontally) build the ground grid; farther
    # ones have no ground height (never ground; dropped by the max_height crop)
    ground_max_distance: float = 200.0
    # m under the robust reference height (ground_outliers.py) below which a point is an outlier
    # (multipath), and m above the sensor above which it is one; None: no such test
    outlier_below: float | None = 1.0
    outlier_above: float | None = 20.0

    def __post_init__(self) -> None:
        for name in ("min_range", "max_range", "max_height", "outlier_below", "outlier_above"):
            v = getattr(self, name)
            if v is not None and not (np.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be a finite number >= 0 (or None), got {v}")
        if self.min_range is not None and self.max_range is not None and self.min_range >= self.max_range:
            raise ValueError(f"min_range ({self.min_range}) must be below max_range ({self.max_range})")
        for name in ("ground_cell", "ground_window", "ground_threshold", "ground_max_distance"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {v}")
        _check_ground_args(self.ground_cell, self.ground_window, self.grid_distance)

    @property
    def grid_distance(self) -> float:
        """Horizontal distance (m) of the points that build the ground grid: the range crop plus
        one window (so the opening near the crop edge sees the same neighbourhood), the crop
        first, so far-away points cannot blow the grid up."""
        if self.max_range is None:
            return self.ground_max_distance
        return self.max_range + self.ground_window
