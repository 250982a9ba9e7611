"""The lidar pipeline's CPU ops (``floxels run``'s per-frame host work): fake registrations and
wrappers. References: :func:`floxels_ext.lidar.preprocess.preprocess_mask_numpy` (cropping and
ground removal), :func:`floxels_ext.lidar.preprocess.transform_points`, the numpy code in
``tests/ops/test_lidar_ops.py`` (flow back into a frame's rows) and in
``tests/lidar/test_bin_disorder_reference.py`` (the .bin reader's scan-order score).

Lidar rows may hold NaN/inf coordinates (kept so outputs line up with the file): these ops
accept them (False in the mask, NaN after a transform) instead of refusing them like the
optimiser's ops. They run without the GIL, single-threaded, on the calling thread.
"""

from __future__ import annotations

import torch

from floxels_ext.ops._checks import check_point_rows
from floxels_ext.ops._lib import ops_ns

__all__ = ["lidar_keep_mask", "lidar_point_classes", "rigid_transform", "lidar_select", "frame_flow",
           "scan_disorder"]


@torch.library.register_fake("floxels::lidar_keep_mask")
def _fake_keep(points, min_range, max_range, max_height, remove_ground, ground_cell, window_cells,
               ground_threshold, ground_max_rise, grid_distance, max_cells, outlier_below, outlier_above):
    return points.new_empty((points.shape[0],), dtype=torch.bool)


@torch.library.register_fake("floxels::lidar_point_classes")
def _fake_classes(points, min_range, max_range, max_height, remove_ground, ground_cell, window_cells,
                  ground_threshold, ground_max_rise, grid_distance, max_cells, outlier_below, outlier_above):
    return points.new_empty((points.shape[0],), dtype=torch.uint8)


@torch.library.register_fake("floxels::rigid_transform")
def _fake_transform(points, transform):
    return torch.empty_like(points)


@torch.library.register_fake("floxels::lidar_select")
def _fake_select(points, mask):
    ctx = torch.library.get_ctx()
    return points.new_empty((ctx.new_dynamic_size(), 3)), points.new_empty((ctx.new_dynamic_size(),), dtype=torch.int64)


@torch.library.register_fake("floxels::frame_flow")
def _fake_frame_flow(flow, mask, nonfinite, rotation, dynamic_threshold):
    n = mask.shape[0]
    return flow.new_empty((n, 3)), mask.new_empty((n,))


def _host_points(points, name: str = "points") -> torch.Tensor:
    check_point_rows(points, name)  # NaN rows allowed: lidar files keep them
    if points.device.type != "cpu":
        raise ValueError(f"{name} must be on the CPU (a lidar pipeline op), got {points.device}")
    return points


def lidar_keep_mask(points: torch.Tensor, *, min_range: float | None, max_range: float | None,
                    max_height: float | None, remove_ground: bool, ground_cell: float, window_cells: int,
                    ground_threshold: float, ground_max_rise: float | None, grid_distance: float,
                    max_cells: int, outlier_below: float | None = None,
                    outlier_above: float | None = None) -> torch.Tensor:
    """(N,) bool: the rows of ``points`` (one scan, sensor frame, z up) kept by cropping, outlier
    and ground removal (the op's schema comment in ``csrc/ops.cpp`` says each argument).
    A ground grid over ``max_cells`` cells raises ValueError."""
    return _keep_op(ops_ns.lidar_keep_mask, points, min_range, max_range, max_height, remove_ground, ground_cell,
                    window_cells, ground_threshold, ground_max_rise, grid_distance, max_cells, outlier_below,
                    outlier_above)


def lidar_point_classes(points: torch.Tensor, *, min_range: float | None, max_range: float | None,
                        max_height: float | None, remove_ground: bool, ground_cell: float, window_cells: int,
                        ground_threshold: float, ground_max_rise: float | None, grid_distance: float,
                        max_cells: int, outlier_below: float | None = None,
                        outlier_above: float | None = None) -> torch.Tensor:
    """(N,) uint8 class of every row, as :func:`lidar_keep_mask` decides it: 0 cropped (or
    non-finite), 1 kept, 2 ground, 3 outlier (``floxels_ext.lidar.preprocess.CROPPED`` ...)."""
    return _keep_op(ops_ns.lidar_point_classes, points, min_range, max_range, max_height, remove_ground, ground_cell,
                    window_cells, ground_threshold, ground_max_rise, grid_distance, max_cells, outlier_below,
                    outlier_above)


def _keep_op(op, points, min_range, max_range, max_height, remove_ground, ground_cell, window_cells,
             ground_threshold, ground_max_rise, grid_distance, max_cells, outlier_below, outlier_above):
    points = _host_points(points)
    try:
        return op(points, min_range, max_range, max_height, bool(remove_ground), float(ground_cell),
                  int(window_cells), float(ground_threshold), ground_max_rise, float(grid_distance), int(max_cells),
                  outlier_below, outlier_above)
    except RuntimeError as e:
        raise ValueError(str(e).split("\n")[0].removeprefix("floxels: lidar_keep_mask: ")) from None


def rigid_transform(points: torch.Tensor, transform: torch.Tensor) -> torch.Tensor:
    """``R p + t`` for every row of ``points`` (N, 3) with a (4, 4) float64 ``transform``,
    computed in float64, returned in ``points``' dtype (NaN rows stay NaN)."""
    points = _host_points(points)
    transform = torch.as_tensor(transform, dtype=torch.float64)
    if transform.shape != (4, 4):
        raise ValueError(f"transform must be (4, 4), got {tuple(transform.shape)}")
    if not bool(torch.isfinite(transform).all()):
        raise ValueError("transform has NaN/inf entries")
    return ops_ns.rigid_transform(points, transform)


def lidar_select(points: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(points[mask] as a contiguous (M, 3) array, indices of the rows with NaN/inf
    coordinates)`` in one pass without the GIL (numpy's boolean indexing and
    ``isfinite(...).all(1)`` of a 240k-point scan took ~7 ms with it). ``points`` (N, 3) may
    have any strides, e.g. the x y z columns of a file's x y z intensity rows."""
    points = _host_points(points)
    mask = torch.as_tensor(mask, dtype=torch.bool)
    if mask.shape != (points.shape[0],):
        raise ValueError(f"mask must have shape ({points.shape[0]},), got {tuple(mask.shape)}")
    return ops_ns.lidar_select(points, mask)


def frame_flow(flow: torch.Tensor, mask: torch.Tensor, nonfinite: torch.Tensor, rotation: torch.Tensor,
               dynamic_threshold: float) -> tuple[torch.Tensor, torch.Tensor]:
    """A frame's flow in its file's rows and axes, and the dynamic flags.

    ``flow`` (M, 3) float32: the flow of the rows where ``mask`` (N,) bool is set, in world
    axes; ``rotation`` (3, 3): the frame's file -> world rotation. Returns ``(flow (N, 3)
    float32, dynamic (N,) bool)``: ``flow @ rotation`` on the masked rows, 0 on the others,
    NaN on the rows listed in ``nonfinite`` (int64); dynamic where |flow| > ``dynamic_threshold``."""
    try:
        return ops_ns.frame_flow(torch.as_tensor(flow, dtype=torch.float32).reshape(-1, 3),
                                 torch.as_tensor(mask, dtype=torch.bool), torch.as_tensor(nonfinite, dtype=torch.int64),
                                 torch.as_tensor(rotation, dtype=torch.float32), float(dynamic_threshold))
    except RuntimeError as e:
        raise ValueError(str(e).split("\n")[0].removeprefix("floxels: frame_flow: ")) from None


def scan_disorder(points: torch.Tensor) -> float:
    """The .bin reader's scan-order score of ``points`` (N, 3) float32/float64, any strides:
    for each of x, y, z over the finite rows, the median |step| between consecutive rows over
    the interquartile range (``np.percentile``'s), and the median of the three; NaN with fewer
    than 16 finite rows (:func:`floxels_ext.lidar.io.readers._disorder`)."""
    return float(ops_ns.scan_disorder(_host_points(points)))
