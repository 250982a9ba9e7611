"""Outliers of a lidar scan far below the ground (multipath) or far above the sensor, found
before the ground surface is built (numpy reference of the C++ op ``floxels::lidar_keep_mask``'s
first steps, ``csrc/cpu/lidar_ground.h``; the torch path calls these functions on its copied-back
grid, so every implementation computes the same numbers).

Why: real scans carry returns metres below the road (multipath: 65-99 per KITTI sweep, 2-18 m
down). Every one of them was the lowest point of its cell, the morphological opening spread it
over a window, the plane fit sank towards them, and the ground surface ended under the road:
nothing was ground, and the height crop measured from that surface removed almost everything.

The reference height, robust to a few hundred such points (``ground_reference``):

1. blocks of ``b x b`` grid cells (``b = window_cells // 4``, 2 m at the defaults): per block,
   the (lower) median of its cells' lowest z (the value at sorted index ``(n - 1) // 2``): a
   clump of multipath returns (one a cell) does not move it where a ring of ground crosses the
   block (a lower quartile did: tests/lidar/test_ground_outliers.py);
2. per block, the lower quartile of those block values over the ``(2R+1)^2`` blocks around it
   (R = :data:`REF_RADIUS_BLOCKS`, 14 m at the defaults, index ``(m - 1) // 4``): a quarter of
   the blocks must be outliers to lower it, and objects (cars, walls, vegetation) raise only
   the blocks they dominate: three quarters of a 14 m neighbourhood would have to be hidden
   ground to raise it;
3. where a neighbourhood holds nothing but outliers (multipath images land behind walls, where
   no ground is seen), steps 1-2 follow them: every block's reference is clamped to a cone
   around the ground near the sensor (the lower median of the references of the blocks within
   :data:`NEAR_GROUND_M` m): ``g0 -/+ (REF_MAX_SLOPE * r + REF_CONE_MARGIN)``, r the block
   centre's horizontal distance, i.e. terrain at most 20 % steep on average from the sensor.

A point is an outlier when it lies more than ``outlier_below`` metres under its block's
reference, or higher than ``outlier_above`` metres above the sensor (the frame's origin).
Outliers build no ground cell, are never kept, and are counted (``floxels run``'s summary).
All selections are exact order statistics (no interpolation), so every implementation picks
the same values.
"""

from __future__ import annotations

import numpy as np

__all__ = ["REF_RADIUS_BLOCKS", "REF_MAX_SLOPE", "REF_CONE_MARGIN", "NEAR_GROUND_M", "block_cells",
           "ground_reference", "outlier_flags"]

REF_RADIUS_BLOCKS = 3     # blocks each side of the reference's neighbourhood (7 x 7 blocks)
REF_MAX_SLOPE = 0.2       # m/m: the cone around the near-sensor ground that bounds the reference
REF_CONE_MARGIN = 1.0     # m: the cone's half-height at the sensor
NEAR_GROUND_M = 15.0      # m: blocks this close (horizontally, centre) give the near-sensor ground


def block_cells(window_cells: int) -> int:
    """Side of a reference block in grid cells: a quarter of the opening window (at least 1)."""
    return max(1, int(window_cells) // 4)


def _order_stat(sorted_vals: np.ndarray, n: np.ndarray, num: int, den: int) -> np.ndarray:
    """The value at index (n - 1) * num // den of each row of sorted values (n finite ones first);
    NaN where n == 0."""
    k = np.maximum((n - 1) * num // den, 0)
    v = np.take_along_axis(sorted_vals, k[..., None], -1)[..., 0].astype(np.float64)
    v[n == 0] = np.nan
    return v


def ground_reference(lowest: np.ndarray, lo_cell: np.ndarray, cell_size: float, window_cells: int) -> np.ndarray:
    """(Hb, Wb) float64: the robust reference height of every block (see the module docstring);
    ``lowest`` (H, W) the lowest z per cell (+inf: empty), ``lo_cell`` the grid's first cell
    (floor(min xy / cell_size)); NaN for blocks without any non-empty block around."""
    from numpy.lib.stride_tricks import sliding_window_view

    b = block_cells(window_cells)
    H, W = lowest.shape
    Hb, Wb = -(-H // b), -(-W // b)
    P = np.full((Hb * b, Wb * b), np.inf)
    P[:H, :W] = lowest
    blk = np.sort(P.reshape(Hb, b, Wb, b).transpose(0, 2, 1, 3).reshape(Hb, Wb, b * b), axis=2)
    q = _order_stat(blk, np.isfinite(blk).sum(2), 1, 2)
    R = REF_RADIUS_BLOCKS
    Q = np.full((Hb + 2 * R, Wb + 2 * R), np.nan)
    Q[R:R + Hb, R:R + Wb] = q
    nb = np.sort(sliding_window_view(Q, (2 * R + 1, 2 * R + 1)).reshape(Hb, Wb, -1), axis=2)  # NaN last
    ref = _order_stat(nb, np.isfinite(nb).sum(2), 1, 4)
    # block centres (same arithmetic as the C++ op): ((index * b + b / 2) + lo) * cell
    cx = ((np.arange(Hb) * b).astype(np.float64) + b / 2.0 + float(lo_cell[0])) * cell_size
    cy = ((np.arange(Wb) * b).astype(np.float64) + b / 2.0 + float(lo_cell[1])) * cell_size
    rb = np.hypot(cx[:, None], cy[None, :])
    near = np.sort(ref[(rb <= NEAR_GROUND_M) & np.isfinite(ref)])
    if len(near):
        g0 = near[(len(near) - 1) // 2]
        spread = REF_MAX_SLOPE * rb + REF_CONE_MARGIN
        lo_b, hi_b = g0 - spread, g0 + spread
        ref = np.where(ref < lo_b, lo_b, np.where(ref > hi_b, hi_b, ref))  # NaN stays NaN
    return ref


def outlier_flags(z: np.ndarray, ij: np.ndarray, ref: np.ndarray, window_cells: int,
                  outlier_below: float | None, outlier_above: float | None) -> np.ndarray:
    """(M,) bool for the grid's points (z, cells ij (M, 2)): more than ``outlier_below`` under
    their block's reference or above ``outlier_above`` (sensor frame z); ``None``: no limit."""
    out = np.zeros(len(z), bool)
    if outlier_below is not None:
        b = block_cells(window_cells)
        out |= z < ref[ij[:, 0] // b, ij[:, 1] // b] - outlier_below
    if outlier_above is not None:
        out |= z > outlier_above
    return out
