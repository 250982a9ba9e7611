"""The machinery of ``floxels run``: reading and preprocessing ahead on worker threads
(``frame_loader``), the optimisation in the calling thread, writing on writer threads or
processes (``frame_writer``; see :func:`run_pipeline`).

Memory stays flat: frames are read at most one chunk ahead (:class:`FrameLoader`), dropped once
behind the current window, and results wait in a bounded queue (the optimiser blocks when the
writer is behind).

Windows and time offsets are exactly those of a serial run: the scans handed to the method are
those of frames ``[lo, hi)`` of each chunk, an unreadable frame an empty scan in its place, all
moved into one world frame re-centred on the first readable frame of the chunk.
"""

from __future__ import annotations

import inspect
import sys
import time

import numpy as np

from floxels_ext.lidar.frame_loader import ChunkScans, FrameLoader
from floxels_ext.lidar.frame_writer import WriterPool

# Python hands the GIL to a waiting thread only every "switch interval" (5 ms by default): with
# reader and writer threads holding it for numpy work, the thread driving the GPU waited that
# long each time it gave it up around a device call. A shorter interval during the run lets it
# back sooner (bench/RESULTS.md, floxels run section); None leaves Python's setting alone.
GIL_SWITCH_INTERVAL: float | None = 0.0005

__all__ = ["plan_chunks", "run_pipeline", "EstimationError"]


def plan_chunks(todo: list[int], chunk: int | None) -> list[list[int]]:
    """Targets per method call. ``chunk``: fixed size; None: 8, 16, 32, then 64 (small first
    calls start the device early while later frames are still being read)."""
    out, k, size = [], 0, (chunk or 8)
    while k < len(todo):
        out.append(todo[k:k + size])
        k += size
        if chunk is None:
            size = min(64, size * 2)
    return out


def _accepts_times(fn) -> bool:
    try:
        return "times" in inspect.signature(fn).parameters
    except (TypeError, ValueError):
        return False


def run_pipeline(*, loader: FrameLoader, writer: WriterPool, method, todo: list[int], n: int, num_scans: int,
                 chunk: int | None, device, options: dict, on_written, next_pose=lambda i: None,
                 times_s=None) -> dict:
    """Estimate every frame of ``todo`` (sorted sequence indices of ``n`` frames).

    ``writer.put(i, prepared, flow_kept, elapsed_s, next_to_world)`` takes each result (``next_pose(i)``,
    called on this thread, gives the last argument: the next frame's pose or None); the writer is
    closed (queued results written) before returning, also on errors and Ctrl-C;
    ``on_written(i)`` (progress) on the calling thread, as results are handed over.
    Returns {"failed": {i: message}, "times": [s/frame], "delivered": count}; raises
    ``EstimationError`` (a ValueError/TypeError of the method before any frame was delivered)."""
    stages = loader.stages
    pad = num_scans - 1
    chunks = plan_chunks(todo, chunk)
    pass_times = times_s is not None and _accepts_times(method.estimate_sequence)
    failed: dict[int, str] = {}
    elapsed: list[float] = []
    delivered = 0
    t_start = time.perf_counter()
    old_interval = sys.getswitchinterval()
    if GIL_SWITCH_INTERVAL is not None:
        sys.setswitchinterval(min(old_interval, GIL_SWITCH_INTERVAL))

    def window(c):
        return max(0, c[0] - pad), min(n, c[-1] + pad + 1)

    try:
        for ci, targets_all in enumerate(chunks):
            lo, hi = window(targets_all)
            loader.evict_below(lo)
            loader.prefetch(range(lo, hi))
            if ci + 1 < len(chunks):  # read the next chunk while this one is optimised
                loader.prefetch(range(*window(chunks[ci + 1])))
            # the first readable frame of the chunk anchors its world frame (float32 precision)
            anchor = None
            for i in range(lo, hi):
                p = loader.get(i)
                if p is not None:
                    anchor = p.to_world[:3, 3].copy()
                    break
            targets = []
            for i in targets_all:
                if loader.get(i) is None:
                    failed[i] = loader.errors.get(i, "unreadable")
                    on_written(i)
                else:
                    targets.append(i)
            if not targets:
                continue
            scans = ChunkScans(loader, lo, hi, anchor)
            t_last = [time.perf_counter()]

            def on_frame(f_local, flow_kept, lo=lo):
                nonlocal delivered
                i = lo + int(f_local)
                now = time.perf_counter()
                dt, t_last[0] = now - t_last[0], now
                elapsed.append(dt)
                flow_kept = np.asarray(flow_kept, np.float32).reshape(-1, 3)
                writer.put(i, loader.get(i), flow_kept, dt, next_pose(i))
                delivered += 1
                on_written(i)

            extra = {"times": list(times_s[lo:hi])} if pass_times else {}
            t0 = time.perf_counter()
            stages.in_estimate = True
            try:
                method.estimate_sequence(scans, [i - lo for i in targets], device, dict(options), on_frame, **extra)
            except (ValueError, TypeError) as e:
                if delivered == 0 and not failed:
                    raise EstimationError(str(e)) from None
                for i in targets:
                    failed.setdefault(i, f"estimation failed: {e}")
                loader.report(f"floxels: error: frames {loader.seq.frames[targets[0]].name}.."
                              f"{loader.seq.frames[targets[-1]].name}: {e}")
            except RuntimeError as e:  # e.g. out of GPU memory: lose this chunk, keep going
                for i in targets:
                    failed.setdefault(i, f"estimation failed: {e}")
                loader.report(f"floxels: error: frames {loader.seq.frames[targets[0]].name}.."
                              f"{loader.seq.frames[targets[-1]].name}: {e}")
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
