"""Distance transforms of the support scans: building one, starting those of a single frame as
its scans are uploaded (:class:`EarlyDts`; on which streams: ``schedule.EdtStreams``), and the
per-window view of a sequence-wide cache."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from floxels_ext.estimator.config import FloxelsConfig
from floxels_ext.estimator.schedule import EdtStreams, upload
from floxels_ext.estimator.sight import Sight, scan_sight, sensor_out_of_reach, warn_sensor_out_of_reach
from floxels_ext.ops import distance_transform
from floxels_ext.ops.grid import grid_from_bounds, point_bounds

__all__ = ["DistanceTransform", "build_dt", "EarlyDts", "WindowCache"]

F = torch.ops.floxels


@dataclass
class DistanceTransform:
    """A support scan's distance transform: float32 (Z, Y, X) metres, sample (0,0,0) at ``origin``."""

    values: torch.Tensor
    origin: list[float]
    sight: Sight | None = None  # what its scan could see (range_mask / visibility with a known sensor)


def build_dt(points: torch.Tensor, cfg: FloxelsConfig, bounds=None, sensor=None,
             ground_of: Callable[[], torch.Tensor | None] | None = None) -> DistanceTransform | None:
    """DT of a validated scan; ``bounds`` (its min/max xyz, see point_bounds) saves a host sync.
    ``sensor`` (the scan's sensor position, xyz in the scans' frame) with ``cfg.range_mask`` or
    ``cfg.visibility``: its :class:`~floxels_ext.estimator.sight.Sight` comes with it, its range
    image with the scan's removed ground returns where ``ground_of()`` gives them (called only
    then: re-centring and uploading them is work no other option needs). A sensor beyond any
    lidar's reach of every point (``sight.sensor_out_of_reach``) is not used, with a warning."""
    if points.shape[0] == 0:
        return None
    if bounds is None:
        values, origin = distance_transform(points, cfg.dt_cell, cfg.dt_padding, max_cells=cfg.max_dt_cells)
        d = DistanceTransform(values, origin)
    else:
        origin, shape = grid_from_bounds(*bounds, cfg.dt_cell, cfg.dt_padding, cfg.max_dt_cells)
        occ = F.points_to_occupancy(points, origin, cfg.dt_cell, shape)
        d = DistanceTransform(F.edt(occ, cfg.dt_cell), origin)
    if (cfg.range_mask or cfg.visibility) and sensor is not None:
        if sensor_out_of_reach(sensor, bounds if bounds is not None else point_bounds([points])[0]):
            warn_sensor_out_of_reach()
            return d
        ground = ground_of() if cfg.visibility and ground_of is not None else None
        if ground is not None:
            ground = upload(ground, points.device)  # on this (the EDT's) stream
        d.sight = scan_sight(points, sensor, band=cfg.range_mask, image=cfg.visibility, ground=ground)
    return d


class EarlyDts:
    """``prepare_scans``' on_ready hook for a single frame on a GPU: each support scan's EDT
    queued (into ``cache``) as soon as its upload is, on a stream of its own (``streams``), so
    the EDTs (the longest work before the optimiser) start while later scans are still being
    copied; ``prepare_group`` then builds what is left on the same streams
    (``FLOXELS_EARLY_DT=0``: all of them, for measurements)."""

    def __init__(self, cfg: FloxelsConfig, cache: dict) -> None:
        self.cfg, self.cache = cfg, cache
        self.streams = EdtStreams()

    def __call__(self, i: int, points: torch.Tensor, bounds, is_target: bool, sensor=None, ground_of=None) -> None:
        if is_target or i in self.cache or points.shape[0] == 0 or not EdtStreams.early(points.device):
            return
        with self.streams.launching(points.device):
            self.cache[i] = build_dt(points, self.cfg, bounds, sensor, ground_of)


class WindowCache:
    """A window's view (index in the window -> DT) of a sequence-wide cache (frame -> DT)."""

    def __init__(self, cache: dict, start: int) -> None:
        self.cache, self.start = cache, start

    def __contains__(self, i) -> bool:
        return self.start + i in self.cache

    def __getitem__(self, i):
        return self.cache[self.start + i]

    def __setitem__(self, i, value) -> None:
        self.cache[self.start + i] = value
