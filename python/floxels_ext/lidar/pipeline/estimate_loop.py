"""The machinery of ``floxels run``: reading and preprocessing ahead on worker threads
(``frame_loader``), the optimisation in the calling thread, writing on writer threads or
processes (``frame_writer``; see :func:`run_pipeline`).

Memory stays flat: frames are read at most ``READ_AHEAD`` frames ahead of the scans the method
asks for (:class:`FrameLoader`, :class:`ChunkScans`), dropped once behind the current window,
and results wait in a bounded queue (the optimiser blocks when the writer is behind).

Windows and time offsets are exactly those of a serial run: the scans handed to the method are
those of frames ``[lo, hi)`` of each chunk, an unreadable frame an empty scan in its place, all
moved into one world frame re-centred on the first readable frame of the chunk.
"""

from __future__ import annotations

import bisect
import sys
import threading
import time

import numpy as np

from floxels_ext.lidar.pipeline.frame_checks import frame_failure
from floxels_ext.lidar.pipeline.frame_loader import ChunkScans, FrameLoader, GroundView, SensorView
from floxels_ext.lidar.pipeline.frame_writer import WriterPool
from floxels_ext.methods import accepts

# Python hands the GIL to a waiting thread only every "switch interval" (5 ms by default): with
# reader and writer threads holding it for numpy work, the thread driving the GPU waited that
# long each time it gave it up around a device call. A shorter interval during the run lets it
# back sooner (bench/RESULTS.md, floxels run section); None leaves Python's setting alone.
GIL_SWITCH_INTERVAL: float | None = 0.0005

# Targets per method call by default. Long calls: each call starts and drains the method's
# pipeline (estimate_sequence prepares the next batch while the device optimises one), which cost
# ~3 ms a frame with calls of 8-64 frames on an H100 (bench/RESULTS.md). The bound: each call has
# one world frame re-centred on its first frame, and 128 frames (12.8 s at 10 Hz, < 400 m at
# 30 m/s) keep float32 coordinates within ~3e-5 m of exact.
DEFAULT_CHUNK = 128
# Frames read (and preprocessed) ahead of the scan the method asks for: memory stays flat
# whatever the chunk, and the method never waits on a sequence the readers outpace.
READ_AHEAD = 64

# Each chunk's world frame is re-centred on a point of this grid (m) near its first frame. Why a
# grid: Floxels' voxel and distance-transform grids are aligned to the coordinates, so a shift by
# anything but a multiple of their cells (0.5 m, 0.1 m) changes the estimate (by up to the
# flow itself after a few iterations), and the flow of a frame would depend on where its chunk
# started: on --chunk, --frames, a resumed run or a Ray task's split. 10 m is a multiple of
# every cell size of 0.1, 0.2, 0.25, 0.5, 1, 2, 2.5 or 5 m.
ANCHOR_GRID = 10.0

__all__ = ["DEFAULT_CHUNK", "READ_AHEAD", "ANCHOR_GRID", "snap_anchor", "chunk_anchor", "plan_chunks", "run_pipeline",
           "EstimationError"]


def snap_anchor(position) -> np.ndarray:
    """The world-frame origin of a chunk whose first frame is at ``position`` (3,): the nearest
    multiple of ``ANCHOR_GRID`` (so results do not depend on where chunks start)."""
    return np.round(np.asarray(position, np.float64) / ANCHOR_GRID) * ANCHOR_GRID


# Points more than this far from their native origin (m) are in a world frame already (map
# scale, UTM); their chunk is re-centred near them instead, on a grid of this step (a multiple
# of ANCHOR_GRID, so the alignment argument above holds; coarse, so that the anchor does not
# depend on which point of the scan is looked at).
FAR_ANCHOR = 1000.0


def chunk_anchor(p) -> np.ndarray:
    """The world-frame origin of a chunk whose first readable frame is ``p`` (a PreparedFrame):
    its native origin (the sensor) snapped to ``ANCHOR_GRID``; for points far from their native
    origin (world-frame files at map scale, whose native origin is the world's: issue 45), a
    point near them snapped to ``FAR_ANCHOR``, so the chunk's float32 coordinates stay small."""
    base = np.asarray(p.to_world[:3, 3], np.float64)
    if len(p.kept):
        sample = np.asarray(p.kept[::max(1, len(p.kept) // 256)], np.float64)
        centre = p.to_world[:3, :3] @ sample.mean(axis=0) + base
        if np.isfinite(centre).all() and np.abs(centre - base).max() > FAR_ANCHOR:
            return np.round(centre / FAR_ANCHOR) * FAR_ANCHOR
    return snap_anchor(base)


def plan_chunks(todo: list[int], chunk: int | None) -> list[list[int]]:
    """Targets per method call: ``chunk`` at a time (None: ``DEFAULT_CHUNK``)."""
    size = chunk or DEFAULT_CHUNK
    return [todo[k:k + size] for k in range(0, len(todo), size)]


def run_pipeline(*, loader: FrameLoader, writer: WriterPool, method, todo: list[int], n: int, num_scans: int,
                 chunk: int | None, device, options: dict, on_written, next_pose=lambda i: None,
                 times_s=None) -> dict:
    """Estimate every frame of ``todo`` (sorted sequence indices of ``n`` frames).

    ``writer.put(i, prepared, flow_kept, elapsed_s, next_to_world, fields)`` takes each result
    (``next_pose(i)``, called on this thread, gives the next frame's pose or None; ``fields``: the
    method's per-point fields of the kept rows, e.g. Floxels' motion evidence, or None); the writer is
    closed (queued results written) before returning, also on errors and Ctrl-C;
    ``on_written(i)`` (progress) on the calling thread, as results are handed over.
    Returns {"failed": {i: message}, "times": [s/frame], "delivered": count}; raises
    ``EstimationError`` (a ValueError/TypeError of the method before any frame was delivered)."""
    stages = loader.stages
    stages.optimiser_thread = threading.get_ident()
    pad = num_scans - 1
    chunks = plan_chunks(todo, chunk)
    pass_times = times_s is not None and accepts(method.estimate_sequence, "times")
    pass_sensors = accepts(method.estimate_sequence, "sensors")
    pass_ground = method.wants_ground(options)  # (the loader keeps the ground for the same test)
    failed: dict[int, str] = {}
    elapsed: list[float] = []
    delivered = 0
    t_start = time.perf_counter()
    old_interval = sys.getswitchinterval()
    if GIL_SWITCH_INTERVAL is not None:
        sys.setswitchinterval(min(old_interval, GIL_SWITCH_INTERVAL))

    def window(c):
        return max(0, c[0] - pad), min(n, c[-1] + pad + 1)

    # every frame some window reads, in order: the readers work through it READ_AHEAD frames
    # ahead of the scan the method asks for (across chunk ends)
    need = sorted({i for c in chunks for i in range(*window(c))})

    def read_ahead(i: int) -> None:
        k = bisect.bisect_left(need, i)
        loader.prefetch(need[k:k + READ_AHEAD])

    try:
        for targets in chunks:
            lo, hi = window(targets)
            loader.evict_below(lo)
            read_ahead(lo)
            # the first readable frame of the chunk anchors its world frame (float32 precision)
            anchor = None
            for i in range(lo, hi):
                p = loader.get(i)
                if p is not None:
                    anchor = chunk_anchor(p)
                    break
            if anchor is None:  # nothing readable: every target fails with its file's error
                for i in targets:
                    failed[i] = loader.errors.get(i, "unreadable")
                    on_written(i)
                continue
            # unreadable targets are found as the method reaches them (it gets an empty scan in
            # their place, as for support scans): waiting for the whole chunk first held the
            # device back by a chunk's reading time
            scans = ChunkScans(loader, lo, hi, anchor, read_ahead=read_ahead)
            t_last = [time.perf_counter()]
            seen: set[int] = set()

            def on_frame(f_local, flow_kept, fields=None, lo=lo):
                nonlocal delivered
                i = lo + int(f_local)
                seen.add(i)
                now = time.perf_counter()
                dt, t_last[0] = now - t_last[0], now
                p = loader.get(i)
                why = None if p is None else frame_failure(method, options, loader, i, n, fields)
                if p is None or why is not None:
                    failed[i] = why or loader.errors.get(i, "unreadable")
                else:
                    elapsed.append(dt)
                    flow_kept = np.asarray(flow_kept, np.float32).reshape(-1, 3)
                    writer.put(i, p, flow_kept, dt, next_pose(i), fields)
                    delivered += 1
                on_written(i)
                loader.evict_below(i - pad)  # frames before this window: no later window reads them
                stages.add("deliver", time.perf_counter() - now)

            extra = {"times": list(times_s[lo:hi])} if pass_times else {}
            if pass_sensors:
                extra["sensors"] = SensorView(scans)
            if pass_ground:
                extra["ground"] = GroundView(scans)
            t0 = time.perf_counter()
            stages.in_estimate = True
            try:
                method.estimate_sequence(scans, [i - lo for i in targets], device, dict(options), on_frame, **extra)
            except (ValueError, TypeError) as e:
                if delivered == 0 and not failed:
                    raise EstimationError(str(e)) from None
                for i in targets:
                    failed.setdefault(i, loader.errors.get(i) or f"estimation failed: {e}")
                loader.report(f"floxels: error: frames {loader.seq.frames[targets[0]].name}.."
                              f"{loader.seq.frames[targets[-1]].name}: {e}")
            except RuntimeError as e:  # e.g. out of GPU memory: lose this chunk, keep going
                for i in targets:
                    failed.setdefault(i, loader.errors.get(i) or f"estimation failed: {e}")
                loader.report(f"floxels: error: frames {loader.seq.frames[targets[0]].name}.."
                              f"{loader.seq.frames[targets[-1]].name}: {e}")
            else:
                for i in targets:  # a method that skipped a target (e.g. an empty scan)
                    if i not in seen and i not in failed:
                        failed[i] = loader.errors.get(i, "the method returned no flow for this frame")
                        on_written(i)
            finally:
                stages.in_estimate = False
                stages.add("estimate", time.perf_counter() - t0)
            scans.close()
            del scans
    finally:
        writer.close()  # results already computed are written, also on Ctrl-C
        loader.close()
        sys.setswitchinterval(old_interval)
        stages.add("wall", time.perf_counter() - t_start)
    for i, msg in writer.failures.items():
        failed[i] = msg
    return {"failed": failed, "times": elapsed, "delivered": delivered, "written": writer.written}


class EstimationError(ValueError):
    """The method rejected its input before any frame was done (bad options, bad scans)."""
