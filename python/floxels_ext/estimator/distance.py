"""Distance transforms of the support scans: building one, starting them on their own CUDA
streams as the scans are uploaded, and the per-window view of a sequence-wide cache."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from floxels_ext.estimator.config import FloxelsConfig
from floxels_ext.estimator.scans import upload
from floxels_ext.estimator.sight import Sight, scan_sight
from floxels_ext.estimator.streams import serial_stages, side_stream
from floxels_ext.ops import distance_transform
from floxels_ext.ops.grid import grid_from_bounds
from floxels_ext.switches import flag

__all__ = ["DistanceTransform", "build_dt", "DtStreams", "WindowCache"]

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
    then: re-centring and uploading them is work no other option needs)."""
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
        ground = ground_of() if cfg.visibility and ground_of is not None else None
        if ground is not None:
            ground = upload(ground, points.device)  # on this (the EDT's) stream
        d.sight = scan_sight(points, sensor, band=cfg.range_mask, image=cfg.visibility, ground=ground)
    return d


class DtStreams:
    """EDTs of a single frame on a GPU, each on a stream of its own (they overlap each
    other's tails). As ``prepare_scans``' on_ready hook (:meth:`__call__`), it queues each
    support scan's EDT as soon as its upload is queued, so the EDTs (the longest work before
    the optimiser) start while later scans are still being copied; ``FLOXELS_EARLY_DT=0``
    leaves them to :func:`~floxels_ext.estimator.group.prepare_group` (measurements)."""

    def __init__(self, cfg: FloxelsConfig, cache: dict | None = None) -> None:
        self.cfg, self.cache = cfg, cache  # cache: where __call__ puts the DTs
        self.start: torch.cuda.Event | None = None  # on the main stream, before the first EDT
        self.streams: list = []  # the streams used, for the main stream to wait for

    def launch(self, points: torch.Tensor, bounds, sensor=None, ground_of=None) -> DistanceTransform | None:
        """Queue the EDT of ``points`` (on a CUDA device) after the current stream's work."""
        main = torch.cuda.current_stream(points.device)
        if self.start is None:
            self.start = torch.cuda.Event(enable_timing=True)
            self.start.record(main)
        st = side_stream(points.device, f"dt{len(self.streams) % 4}")
        st.wait_stream(main)  # the upload
        with torch.cuda.stream(st):
            d = build_dt(points, self.cfg, bounds, sensor, ground_of)
        self.streams.append(st)
        return d

    def __call__(self, i: int, points: torch.Tensor, bounds, is_target: bool, sensor=None, ground_of=None) -> None:
        dev = points.device
        if dev.type != "cuda" or serial_stages(dev) or is_target or i in self.cache or points.shape[0] == 0:
            return
        if not flag("FLOXELS_EARLY_DT"):
            return
        self.cache[i] = self.launch(points, bounds, sensor, ground_of)


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
