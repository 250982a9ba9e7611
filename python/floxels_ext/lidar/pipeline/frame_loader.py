"""Reading and preprocessing one frame for ``floxels run``, and doing so ahead of the optimiser.

:func:`load_frame` reads one frame file, crops it and removes its ground (the compiled CPU op,
or torch on a GPU) and checks it (:mod:`floxels_ext.lidar.pipeline.frame_checks`), giving a
:class:`PreparedFrame`; :class:`FrameLoader` runs it on worker threads (or processes), as far
ahead as the caller prefetches, and keeps what each frame said (errors, non-finite rows, point
classes) for the run's summary. File reads and the lidar ops (cropping, ground removal, row
selection) run without the GIL, and frames are hundreds of kB, so threads overlap them with the
optimiser without copying frames between processes. Moving the frames into a chunk's world
frame is the engine's (``lidar/dataset/layout.py``: ``StreamScans``).
"""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from floxels_ext.lidar.pipeline.frame_checks import empty_crop_message, far_outliers, finite_mask
from floxels_ext.lidar.pipeline.stages import Stages
from floxels_ext.lidar.preprocess.transform import transform_points

__all__ = ["PreparedFrame", "load_frame", "single_threaded_blas", "LoaderPools", "FrameLoader"]


@dataclass
class PreparedFrame:
    kept: np.ndarray         # (M, 3) float32 (float64 for float64 files): the optimised points, native
                             # coordinates, file order
    mask: np.ndarray         # (N,) bool: which rows of the file they are
    nonfinite: np.ndarray    # indices of the rows with NaN/inf coordinates
    to_world: np.ndarray     # (4, 4) native -> world
    points: np.ndarray | None = None  # (N, 3) all rows, only when asked for (--self-contained)
    crc: int | None = None   # outputs.points_crc32 of all rows: read-back checks (floxels show)
    # points per preprocess class (kept, ground, outlier, cropped: non-finite rows included);
    # None without preprocessing
    counts: dict | None = None
    # the sensor's position in the world frame (the native frame's origin, or the file's pose
    # for points already in the world frame); None where unknown. Floxels' range_mask.
    sensor: np.ndarray | None = None
    # (G, 3) float32 (float64 for float64 files): the returns preprocessing classed as ground, native coordinates; only when
    # the method reads them (Floxels' visibility: its range images), else None
    ground: np.ndarray | None = None

    @property
    def n(self) -> int:
        return len(self.mask)


def load_frame(i: int, seq, settings, pose_mode: str, poses, keep_points: bool, pre_device=None,
               keep_ground: bool = False) -> dict:
    """Read and preprocess frame ``i`` (runs on a worker thread or process). Returns a dict:
    ``frame`` (a PreparedFrame) or ``error`` (a message naming the file), ``warning``, and the
    seconds spent reading and preprocessing. ``pose_mode``: "table" (``poses[i]``), "frame" (the
    file's own ``pose``), "identity" (no ego-motion) or "seqio" (points already in the world
    frame; the file's ``pose`` locates the sensor for cropping). ``keep_ground``: the frame keeps
    its ground returns (``PreparedFrame.ground``)."""
    from floxels_ext.lidar.io import LidarFormatError, MissingDependencyError
    from floxels_ext.lidar.io.outputs import points_crc32
    from floxels_ext.lidar.pipeline.frame_checks import beyond_ground_grid, float32_far_message
    from floxels_ext.lidar.preprocess.masks import preprocess_classes
    from floxels_ext.lidar.preprocess.settings import GROUND, KEPT
    from floxels_ext.lidar.preprocess.transform import host_rows
    from floxels_ext.ops.lidar import lidar_select

    path = seq.frames[i].path
    out: dict = {"read": 0.0, "preprocess": 0.0}
    t0 = time.perf_counter()
    try:
        scan = seq.load(i)
        sensor_from_native = None
        sensor = None
        if pose_mode == "seqio":
            to_world = np.eye(4)
            if scan.pose is not None:
                sensor_from_native = np.linalg.inv(scan.pose)
                sensor = np.asarray(scan.pose, np.float64)[:3, 3].copy()
            else:
                out["warning"] = "no_pose"
        elif pose_mode == "frame":
            if scan.pose is None:
                raise LidarFormatError(f"{path}: no 'pose' in this frame, but other frames of the sequence "
                                       f"have one (give --poses)")
            to_world = scan.pose
        elif pose_mode == "identity":
            to_world = np.eye(4)
        else:  # "table": seq.poses or odometry
            to_world = poses[i]
    except MissingDependencyError:
        raise
    except (LidarFormatError, ValueError, OSError) as e:
        out["error"] = str(e)
        return out
    pts = scan.points if scan.points.dtype == np.float32 else scan.points.astype(np.float32)
    # float64 files: the points kept, the ground and the sensor-frame points come from the
    # float64 rows, so map-scale coordinates keep their precision until the engine re-centres
    # them (issue 45); float32 files far out have lost it already: said once
    exact = scan.exact if scan.exact is not None else pts
    if exact is pts:
        far = float32_far_message(path, pts)
        if far:
            out["far_float32"] = far
    t1 = time.perf_counter()
    out["read"] = t1 - t0
    rows = host_rows(pts)  # the file's x y z columns, viewed (the ops read any strides)
    exact_rows = rows if exact is pts else host_rows(exact)
    pts_sensor = exact if sensor_from_native is None else transform_points(exact, sensor_from_native)
    classes = None
    try:
        if settings is None:
            mask = finite_mask(rows)
        elif pre_device is not None and str(pre_device).startswith("cuda"):
            import torch

            # a stream per worker thread: its kernels and read-back do not queue behind the optimiser's
            if getattr(_TLS, "stream", None) is None:
                _TLS.stream = torch.cuda.Stream(device=pre_device)
            with torch.cuda.stream(_TLS.stream):
                classes = preprocess_classes(pts_sensor, settings, device=pre_device)
        else:
            classes = preprocess_classes(pts_sensor, settings)  # the compiled CPU op: no GIL while it runs
        if classes is not None:
            mask = classes == KEPT
    except ValueError as e:
        out["error"] = f"{path}: preprocessing failed: {e}"
        return out
    kept, nonfinite = lidar_select(exact_rows, mask)  # one pass without the GIL
    nonfinite = nonfinite.numpy()
    if len(nonfinite) == len(pts):
        out["error"] = f"{path}: no finite points (all {len(pts)} rows have NaN/inf coordinates)"
        return out
    if settings is not None and kept.shape[0] == 0:
        # nothing to optimise: an all-zero flow would pass for a real result (issue 30)
        out["error"] = empty_crop_message(path, pts_sensor, settings, pose_mode)
        out["empty_crop"] = True
        return out
    kept_np = kept.numpy()
    stray = far_outliers(kept_np)
    if stray is not None:
        out["stray"] = f"{path}: " + stray
    out["preprocess"] = time.perf_counter() - t1
    counts = ground = None
    if classes is not None:
        # per class, not np.bincount: that converts the (N,) uint8 classes to int64 first (~4x the time)
        n = [int(np.count_nonzero(classes == c)) for c in range(4)]
        counts = {"kept": n[1], "ground": n[2], "outlier": n[3], "cropped": n[0]}
        if settings.remove_ground and counts["ground"] == 0:
            beyond = beyond_ground_grid(path, pts_sensor, settings, pose_mode)
            if beyond:
                out["no_ground"] = beyond
        if keep_ground:
            ground = lidar_select(exact_rows, classes == GROUND)[0].numpy()
    to_world = np.asarray(to_world, np.float64)
    if pose_mode != "seqio":
        sensor = to_world[:3, 3].copy()  # the native frame's origin: the sensor
    out["frame"] = PreparedFrame(kept_np, mask, nonfinite, to_world,
                                 np.ascontiguousarray(pts) if keep_points else None,
                                 None if keep_points else points_crc32(pts), counts, sensor, ground)
    return out


_TLS = threading.local()
_WORKER: dict = {}


def single_threaded_blas():
    """A context limiting numpy's BLAS to one thread (a no-op without threadpoolctl).

    Why: the per-scan BLAS calls (the ground plane's least squares, 3x3 transforms of 100k
    points) are tiny; from 16 workers, each spinning up a 16-thread BLAS pool, they ran ~5x slower
    than on one thread (84 ms a 240k-point scan on a 16-core host). Results are unchanged: each
    output element is computed by the same kernel whatever the thread count."""
    import contextlib

    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        return contextlib.nullcontext()
    return threadpool_limits(limits=1, user_api="blas")


def _init_process(kwargs) -> None:
    _WORKER["blas"] = single_threaded_blas()  # kept alive: the limit holds for the worker's life
    _WORKER["blas"].__enter__()
    _WORKER["kwargs"] = kwargs


def _process_load(i: int) -> dict:
    return load_frame(i, **_WORKER["kwargs"])


def _process_load_kw(i: int, kwargs: dict) -> dict:
    return load_frame(i, **kwargs)


class LoaderPools:
    """The reader threads (or processes) and the two transform threads of a run; a dataset's
    loaders share one set, so the readers of the next sequence are the same warm threads and
    start while the method still works on the current one. ``init_kwargs``: processes hold
    one sequence's reading arguments (a run of one sequence); without them each read carries its own."""

    def __init__(self, workers: int, kind: str = "thread", init_kwargs: dict | None = None) -> None:
        workers = max(1, workers)
        self.kind, self.fixed = kind, init_kwargs is not None
        if kind == "process":
            from floxels_ext.lidar.pipeline.worker_processes import process_pool

            self.read = process_pool(workers, _init_process, (init_kwargs,))
        else:
            self.read = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="floxels-read")
        # transforms wait for loads: a pool of their own, so they never queue behind later loads;
        # two threads: a transform is one op call of ~1 ms (more threads only contend for the GIL)
        self.move = ThreadPoolExecutor(max_workers=min(workers, 2), thread_name_prefix="floxels-move")

    def close(self) -> None:
        self.move.shutdown(wait=True, cancel_futures=True)
        self.read.shutdown(wait=True, cancel_futures=True)


class FrameLoader:
    """Reads and preprocesses frames ahead of use (:meth:`prefetch`) on ``workers`` threads, or
    processes (``kind="process"``: CPU preprocessing without sharing the GIL with the optimiser's
    host work; started at construction, see :mod:`floxels_ext.lidar.pipeline.worker_processes`).
    ``pools``: shared :class:`LoaderPools` (a dataset's sequences), which :meth:`close` leaves
    open; without them the loader makes its own (one sequence: worker processes then hold its
    reading arguments once instead of receiving them with every frame)."""

    def __init__(self, seq, settings, poses, pose_mode: str, report, *, workers: int = 4, kind: str = "thread",
                 pre_device=None, keep_points: bool = False, stages: Stages | None = None, warn,
                 pools: LoaderPools | None = None, keep_ground: bool = False) -> None:
        self.seq, self.report, self.warn = seq, report, warn
        self.stages = stages or Stages()
        self.kwargs = dict(seq=seq, settings=settings, pose_mode=pose_mode, poses=poses, keep_points=keep_points,
                           keep_ground=keep_ground)
        self._own_pools = pools is None
        if pools is None:
            pools = LoaderPools(workers, kind, self.kwargs if kind == "process" else None)
        self.pools, self.pool, self.tpool = pools, pools.read, pools.move
        if pools.kind == "process" and pools.fixed:
            self._submit = lambda i: self.pool.submit(_process_load, i)
        elif pools.kind == "process":
            self._submit = lambda i: self.pool.submit(_process_load_kw, i, self.kwargs)
        else:
            self._submit = lambda i: self.pool.submit(load_frame, i, pre_device=pre_device, **self.kwargs)
        self.futures: dict = {}
        self.done: dict[int, PreparedFrame | None] = {}
        self.errors: dict[int, str] = {}
        self.nonfinite: dict[int, int] = {}
        self.empty_crop: set[int] = set()  # frames with points but none left after cropping
        self.stray: dict[int, str] = {}  # frames whose far outliers blow up a distance transform
        self.counts: dict[int, dict] = {}  # frame -> PreparedFrame.counts (run summary)
        self._warned_no_pose = False
        self._warned_far = False
        self._warned_no_ground = False
        self._lock = threading.Lock()

    def prefetch(self, indices) -> None:
        with self._lock:
            for i in indices:
                if i not in self.futures and i not in self.done:
                    self.futures[i] = self._submit(i)

    def _collect(self, i: int, res: dict) -> PreparedFrame | None:
        with self._lock:
            if i in self.done:
                return self.done[i]
            self.stages.add("read", res["read"])
            self.stages.add("preprocess", res["preprocess"])
            fr = res.get("frame")
            if "error" in res:
                self.errors[i] = res["error"]
                if res.get("empty_crop"):
                    self.empty_crop.add(i)
            else:
                if len(fr.nonfinite):
                    self.nonfinite[i] = len(fr.nonfinite)
                if fr.counts is not None:
                    self.counts[i] = fr.counts
            first_stray = "stray" in res and not self.stray
            if "stray" in res:
                self.stray[i] = res["stray"]
            first_no_pose = res.get("warning") == "no_pose" and not self._warned_no_pose
            self._warned_no_pose |= first_no_pose
            first_far = "far_float32" in res and not self._warned_far
            self._warned_far |= first_far
            first_no_ground = "no_ground" in res and not self._warned_no_ground
            self._warned_no_ground |= first_no_ground
            self.done[i] = fr
        if "error" in res:
            self.report(f"floxels: error: {res['error']}")
        if first_stray:  # once: the summary lists every such frame
            self.warn(res["stray"] + " (further frames like it are listed in the run summary)")
        if first_far:  # once: the precision was lost when the files were written
            self.warn(res["far_float32"])
        if first_no_ground:
            self.warn(res["no_ground"] + " (said for the first such frame)")
        if first_no_pose:
            self.warn(f"{self.seq.frames[i].path} has no 'pose': ranges and heights are measured from the world origin")
        return fr

    def get(self, i: int) -> PreparedFrame | None:
        """Frame ``i`` (None if it cannot be used); waits for it. Thread-safe."""
        with self._lock:
            if i in self.done:
                return self.done[i]
            fut = self.futures.get(i)
            if fut is None:
                fut = self.futures[i] = self._submit(i)
        if not fut.done():
            t0 = time.perf_counter()
            fut.result()
            self.stages.waited(time.perf_counter() - t0)
        fr = self._collect(i, fut.result())
        with self._lock:
            self.futures.pop(i, None)
        return fr

    def peek(self, i: int) -> PreparedFrame | None:
        """The frame if it is loaded already (never waits)."""
        if i in self.done:
            return self.done[i]
        fut = self.futures.get(i)
        if fut is None or not fut.done() or fut.exception() is not None:
            return None
        return self._collect(i, fut.result())

    def evict_below(self, lo: int) -> None:
        with self._lock:
            for k in [k for k in self.futures if k < lo]:
                self.futures.pop(k).cancel()
            for k in [k for k in self.done if k < lo]:
                del self.done[k]

    def release(self) -> None:
        """Drops every frame and cancels the reads not started (the sequence is done); what it
        recorded of its frames (errors, counts) stays for the summary."""
        with self._lock:
            for fut in self.futures.values():
                fut.cancel()
            self.futures.clear()
            self.done.clear()

    def close(self) -> None:
        """:meth:`release`, and its own pools stopped (shared ones stay open)."""
        self.release()
        if self._own_pools:
            self.pools.close()
