"""The per-scan preprocessing of :mod:`floxels_ext.lidar.preprocess` in torch, for the GPU.

Same steps, same float64 arithmetic, same masks as :func:`floxels_ext.lidar.preprocess.masks.preprocess_mask`
(tests run both on CPU tensors and compare): the lowest-point map is a ``scatter_reduce``
(amin), the min/max filters of the morphological opening are ``max_pool2d`` (its implicit -inf
padding is the numpy path's constant border), and the two steps on the small grid run in numpy
on a copy (the outliers' block references, :mod:`floxels_ext.lidar.preprocess.ground_outliers`, and the
trimmed plane fit), so both paths pick the same references and fit exactly the same plane. Per 200k-point scan
the host path costs tens of ms of one core; this moves the per-point work to the device.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from floxels_ext.lidar.preprocess.ground_outliers import block_cells, ground_reference
from floxels_ext.lidar.preprocess.ground_plane import _plane_cap
from floxels_ext.lidar.preprocess.settings import (CROPPED, GROUND, KEPT, MAX_GROUND_CELLS, OUTLIER, Preprocess,
                                                   _window_cells)

__all__ = ["preprocess_mask_torch", "preprocess_classes_torch"]


def _lowest(flat: torch.Tensor, z: torch.Tensor, cells: int) -> torch.Tensor:
    lowest = torch.full((cells,), float("inf"), dtype=torch.float64, device=z.device)
    return lowest.scatter_reduce_(0, flat, z, reduce="amin")


def _outliers(q, ij, lowest, lo, shape, size, settings: Preprocess) -> torch.Tensor:
    """(M,) bool: step 0's outliers among the grid's points q (the references in numpy)."""
    bad = torch.zeros(len(q), dtype=torch.bool, device=q.device)
    if settings.outlier_below is not None:
        ref = ground_reference(lowest.view(shape).cpu().numpy(), lo.cpu().numpy(), settings.ground_cell, size)
        ref = torch.from_numpy(ref).to(q.device)
        b = block_cells(size)
        bad |= q[:, 2] < ref[ij[:, 0] // b, ij[:, 1] // b] - settings.outlier_below
    if settings.outlier_above is not None:
        bad |= q[:, 2] > settings.outlier_above
    return bad


def _opened_surface(q: torch.Tensor, settings: Preprocess):
    """(ij (M,2) long, opened (H,W) float64 on q's device, outlier (M,) bool) of the grid built
    from points q (M,3)."""
    cell = settings.ground_cell
    lo = torch.floor(q[:, :2].amin(0) / cell)
    hi = torch.floor(q[:, :2].amax(0) / cell)
    shape = [int(v) for v in (hi - lo + 1).tolist()]
    if shape[0] * shape[1] > MAX_GROUND_CELLS:
        raise ValueError(f"points spread over {shape[0] * cell:.0f} x {shape[1] * cell:.0f} m: "
                         f"the ground grid would exceed {MAX_GROUND_CELLS:,} cells; crop them (max_distance)")
    ij = (torch.floor(q[:, :2] / cell) - lo).long()
    flat = ij[:, 0] * shape[1] + ij[:, 1]
    lowest = _lowest(flat, q[:, 2], shape[0] * shape[1])
    size = _window_cells(settings.ground_window, cell)
    bad = torch.zeros(len(q), dtype=torch.bool, device=q.device)
    if settings.outlier_below is not None or settings.outlier_above is not None:
        bad = _outliers(q, ij, lowest, lo, shape, size, settings)
        if bool(bad.any()):
            lowest = _lowest(flat[~bad], q[~bad, 2], shape[0] * shape[1])
    grid = lowest.view(1, 1, *shape)
    # min filter with +inf outside the grid == -maxpool(-x) (max_pool2d pads with -inf)
    eroded = -F.max_pool2d(-grid, size, stride=1, padding=size // 2)
    eroded = torch.where(torch.isfinite(eroded), eroded, torch.full_like(eroded, float("-inf")))
    opened = F.max_pool2d(eroded, size, stride=1, padding=size // 2)[0, 0]
    return ij, opened, bad


def preprocess_mask_torch(points_sensor, settings: Preprocess = Preprocess(), device="cpu") -> np.ndarray:
    """:func:`floxels_ext.lidar.preprocess.masks.preprocess_mask` computed with torch on ``device``;
    ``points_sensor`` a numpy array or tensor (N, 3). Returns a numpy (N,) bool array."""
    return preprocess_classes_torch(points_sensor, settings, device) == KEPT


def preprocess_classes_torch(points_sensor, settings: Preprocess = Preprocess(), device="cpu") -> np.ndarray:
    """:func:`floxels_ext.lidar.preprocess.masks.preprocess_classes` computed with torch on ``device``;
    returns a numpy (N,) uint8 array."""
    p = torch.as_tensor(np.asarray(points_sensor) if not torch.is_tensor(points_sensor) else points_sensor)
    p = p.to(device=device).to(torch.float64)  # copy as stored (float32: half the bytes), widen there
    finite = torch.isfinite(p).all(1)
    r = torch.hypot(p[:, 0], p[:, 1])
    in_range = finite.clone()
    if settings.min_range is not None:
        in_range &= r >= settings.min_range
    if settings.max_range is not None:
        in_range &= r <= settings.max_range
    cls = torch.full((len(p),), CROPPED, dtype=torch.uint8, device=p.device)
    need_surface = settings.remove_ground or settings.max_height is not None
    if not need_surface:
        keep = in_range & (p[:, 2] <= settings.max_height) if settings.max_height is not None else in_range
        cls[keep] = KEPT
        return cls.cpu().numpy()
    in_grid = finite & (r <= settings.grid_distance)
    surface = torch.full((len(p),), float("nan"), dtype=torch.float64, device=p.device)
    outlier = torch.zeros(len(p), dtype=torch.bool, device=p.device)
    if bool(in_grid.any()):
        idx = torch.nonzero(in_grid).squeeze(1)
        ij, opened, bad = _opened_surface(p[idx], settings)
        if settings.ground_max_rise is not None:
            capped = _plane_cap(opened.cpu().numpy(), settings.ground_cell, settings.ground_max_rise)
            opened = torch.from_numpy(capped).to(p.device)
        surface[idx] = opened[ij[:, 0], ij[:, 1]]
        outlier[idx] = bad
    height = p[:, 2] - surface  # NaN where no surface: fails both tests below, as in numpy
    low_enough = height <= settings.max_height if settings.max_height is not None else torch.ones_like(in_range)
    ground = height < settings.ground_threshold if settings.remove_ground else torch.zeros_like(in_range)
    cls[in_range & low_enough & ~ground] = KEPT
    cls[in_range & low_enough & ground] = GROUND
    cls[in_range & outlier] = OUTLIER
    return cls.cpu().numpy()
