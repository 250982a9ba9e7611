"""CUDA streams of the estimator: the persistent side streams (DBSCAN and sorting at high
priority, the memory-bound EDTs at normal priority) and the bookkeeping that lets tensors made
on one stream be used on another. On the CPU, or with ``FLOXELS_SERIAL_STAGES=1``, every stage
runs in order on the current stream."""

from __future__ import annotations

import torch

from floxels_ext.switches import flag

__all__ = ["side_stream", "dt_stream", "serial_stages", "sync_device", "used_on"]

_SIDE_STREAMS: dict = {}


def side_stream(device: torch.device, kind: str = "side"):
    """Persistent side streams per device (a new stream per frame would strand cached
    allocator blocks on streams never used again). "side" (DBSCAN, sorting: short kernels
    whose results the host waits for) has high priority, so that its kernels are scheduled
    ahead of the optimiser's queued blocks; "dt" (the EDTs, long and memory bound) has
    normal priority."""
    key = (device.index if device.index is not None else torch.cuda.current_device(), kind)
    if key not in _SIDE_STREAMS:
        # (a priority beyond the device's range maps to its highest)
        _SIDE_STREAMS[key] = torch.cuda.Stream(device=torch.device("cuda", key[0]),
                                               priority=-8 if kind == "side" else 0)
    return _SIDE_STREAMS[key]


def dt_stream(device: torch.device):
    return side_stream(device, "dt")


def serial_stages(device: torch.device) -> bool:
    return device.type != "cuda" or flag("FLOXELS_SERIAL_STAGES")


def sync_device(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def used_on(stream, items, problems, orders, labels) -> None:
    """Tensors made on another stream and used on ``stream``: keep the caching allocator
    from handing their memory out again while ``stream`` may still use it."""
    for pr, order in zip(problems, orders):
        if pr is not None:
            for t in (pr.points, pr.corners.corner_idx, pr.corners.corner_w, pr.corners.vertices, order, pr.labels,
                      *pr.dts, *(pr.segments or ())):
                if t is not None:
                    t.record_stream(stream)
    for lab in labels:
        if lab is not None:
            lab.record_stream(stream)
    for prep, _ in items:
        prep.finite_masks[prep.target].record_stream(stream)
