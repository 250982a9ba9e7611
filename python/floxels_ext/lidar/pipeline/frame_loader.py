"""Frames read and preprocessed ahead of the optimiser for ``floxels run``.

:class:`FrameLoader` reads, checks, crops and removes the ground of frames on worker threads
(or processes), as far ahead as the caller prefetches; :class:`ChunkScans` hands a chunk's
frames to the method as scans in one world frame, lazily, so the first windows start before the
chunk is read; :class:`Stages` adds up where the time went. File reads and the lidar ops
(cropping, ground removal, row selection, transforms) run without the GIL, and frames are
hundreds of kB, so threads overlap them with the optimiser without copying frames between
processes.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from floxels_ext.lidar.preprocess.transform import transform_points

__all__ = ["PreparedFrame", "Stages", "load_frame", "single_threaded_blas", "LoaderPools", "FrameLoader", "ChunkScans"]


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


@dataclass
class Stages:
    """Seconds per stage. read/preprocess/write: summed over worker threads (CPU time spent);
    wait_input: the optimiser waited for frames; estimate: inside the method; wait_writer: the
    optimiser waited for the writer (queue full); deliver: the optimiser handed results over (its
    callback per frame, wait_writer included); wall: the whole pipeline. ``wait_input_in_estimate``:
    the part of wait_input spent inside the method (it asks for the scans lazily), so
    ``estimate - wait_input_in_estimate`` is the time the method actually computed."""

    read: float = 0.0
    preprocess: float = 0.0
    transform: float = 0.0
    estimate: float = 0.0
    write: float = 0.0
    wait_input: float = 0.0
    wait_input_in_estimate: float = 0.0
    wait_writer: float = 0.0
    deliver: float = 0.0
    wall: float = 0.0
    in_estimate: bool = False  # set by the thread calling the method
    optimiser_thread: int | None = None  # its threading.get_ident(): only its waits count
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def waited(self, dt: float) -> None:
        """The calling thread waited ``dt`` s for a frame: counted when it is the optimiser's
        thread (the transform threads wait for loads too, but the device does not)."""
        if self.optimiser_thread is not None and threading.get_ident() != self.optimiser_thread:
            return
        self.add("wait_input", dt)
        if self.in_estimate:
            self.add("wait_input_in_estimate", dt)

    def add(self, name: str, dt: float) -> None:
        with self._lock:
            setattr(self, name, getattr(self, name) + dt)

    def as_dict(self) -> dict:
        d = {k: round(getattr(self, k), 6) for k in
             ("read", "preprocess", "transform", "estimate", "write", "wait_input", "wait_input_in_estimate",
              "wait_writer", "deliver", "wall")}
        # the method waits for nothing but its own work: the rest of the wall time is host-bound
        d["compute"] = round(max(0.0, self.estimate - self.wait_input_in_estimate - self.wait_writer), 6)
        d["outside_estimate"] = round(max(0.0, self.wall - self.estimate), 6)
        d["host_bound"] = round(max(0.0, self.wall - d["compute"]), 6)
        return d


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
    # float64 rows, so map-scale coordinates keep their precision until ChunkScans re-centres
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
        n = np.bincount(classes, minlength=4)
        counts = {"kept": int(n[1]), "ground": int(n[2]), "outlier": int(n[3]), "cropped": int(n[0])}
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


# A support scan's distance transform at the Floxels defaults (0.1 m cells, 2 m padding, float32)
# over the axis-aligned extent of its points: a few stray returns far from the rest (--max-range
# none) multiply it (one point 1 km away: 5.6 GB instead of 0.79 GB). Warned about above this
# size when the scan's bulk alone would need a quarter of it or less.
STRAY_DT_BYTES = 1e9
STRAY_SPAN = 150.0  # m: scans whose coordinates all lie within this span are not examined further


def _dt_bytes(lo, hi, cell: float = 0.1, padding: float = 2.0) -> float:
    return 4.0 * float(np.prod((np.asarray(hi, np.float64) - lo + 2 * padding) / cell + 1))


def far_outliers(kept: np.ndarray) -> str | None:
    """A warning when a few points far from the rest of a scan blow up its distance transform
    (see ``STRAY_DT_BYTES``), else None. Cheap: bounds of all points, quantiles of a sample."""
    if len(kept) < 100:
        return None
    flat = kept.reshape(-1)  # one contiguous pass (per-column reductions cost ~100x more)
    if float(flat.max()) - float(flat.min()) < STRAY_SPAN:  # every axis spans less: nothing to find
        return None
    lo = np.array([kept[:, k].min() for k in range(3)], np.float64)
    hi = np.array([kept[:, k].max() for k in range(3)], np.float64)
    full = _dt_bytes(lo, hi)
    if full < STRAY_DT_BYTES:
        return None
    sample = kept[::max(1, len(kept) // 4096)].astype(np.float64)
    blo = np.maximum(np.percentile(sample, 0.5, axis=0) - 10.0, lo)  # the bulk, 10 m margin
    bhi = np.minimum(np.percentile(sample, 99.5, axis=0) + 10.0, hi)
    bulk = _dt_bytes(blo, bhi)
    if full < 4 * bulk:
        return None
    far = int(((kept < blo - 50.0) | (kept > bhi + 50.0)).any(axis=1).sum())  # clearly apart from the bulk
    dims = lambda a, b: " x ".join(f"{v:.0f}" for v in b - a)  # noqa: E731
    return (f"{far} point(s) lie far outside the rest of the scan (it spans {dims(lo, hi)} m, its bulk "
            f"{dims(blo, bhi)} m): each distance transform of it needs ~{full / 1e9:.1f} GB instead of "
            f"~{bulk / 1e9:.2f} GB (and more time); if they are stray returns, crop them (--max-range, --max-height)")


def empty_crop_message(path, pts_sensor: np.ndarray, settings, pose_mode: str) -> str:
    """Why a frame with finite points has none left after cropping and ground removal, with
    the likely mistake: points not in the frame the ranges are measured in (the sensor at the
    origin), or a crop that removes the whole scan."""
    p = np.asarray(pts_sensor, np.float64)
    p = p[np.isfinite(p).all(axis=1)]
    r = np.hypot(p[:, 0], p[:, 1])
    lo, hi = float(r.min()), float(r.max())
    crop = ", ".join(f"--{k.replace('_', '-')} {getattr(settings, k)}" for k in ("min_range", "max_range", "max_height")
                     if getattr(settings, k) is not None)
    msg = (f"{path}: no point left to optimise after cropping ({crop}) and ground removal; its {len(p)} finite "
           f"points lie {lo:.1f} to {hi:.1f} m from the sensor origin (horizontally)")
    if settings.max_range is not None and lo > settings.max_range:
        return msg + (". Likely a wrong frame: ranges are measured from each scan's sensor origin, and points in a "
                      "world/map frame need their sensor pose ('pose' in the file, --points-frame world" +
                      ("; --no-ego-motion measures from the world origin" if pose_mode == "identity" else "") +
                      "), or check --poses/--calib; else widen --max-range")
    return msg + ". Likely a wrong crop: check --min-range/--max-range/--max-height and the ground settings"


def finite_mask(rows) -> np.ndarray:
    """(N,) bool: the rows with finite coordinates (the keep op with nothing to crop)."""
    from floxels_ext.ops.lidar import lidar_keep_mask

    return lidar_keep_mask(rows, min_range=None, max_range=None, max_height=None, remove_ground=False,
                           ground_cell=1.0, window_cells=1, ground_threshold=0.0, ground_max_rise=None,
                           grid_distance=1.0, max_cells=1).numpy()


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
    one sequence's reading arguments (the plain run); without them each read carries its own."""

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
    ``pools``: shared :class:`LoaderPools` (a dataset's sequences), which :meth:`close` leaves open."""

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

    def close(self) -> None:
        with self._lock:
            for fut in self.futures.values():
                fut.cancel()
            self.futures.clear()
            self.done.clear()
        if self._own_pools:
            self.pools.close()


class ChunkScans(Sequence):
    """The ego-motion-compensated scans of frames ``[lo, hi)`` as a sequence: item ``k`` is frame
    ``lo + k``'s kept points moved into the chunk's world frame (re-centred on ``anchor``). The
    transforms run on the loader's transform threads, at most ``TRANSFORM_AHEAD`` items ahead of
    the one asked for (``read_ahead(frame)`` is called with it: the caller's read-ahead); an item
    is dropped once a later window starts after it."""

    TRANSFORM_AHEAD = 32  # two batches of windows: the method prepares the next batch early

    def __init__(self, loader: FrameLoader, lo: int, hi: int, anchor: np.ndarray, read_ahead=None) -> None:
        self.loader, self.lo, self.hi, self.anchor = loader, lo, hi, anchor
        self._read_ahead = read_ahead or (lambda i: loader.prefetch(range(i, hi)))
        self._futs: dict = {}
        self._next = 0  # transforms are submitted for items < _next
        self._advance(0)

    def _advance(self, k: int) -> None:
        self._read_ahead(self.lo + k)
        stop = min(len(self), k + self.TRANSFORM_AHEAD)
        while self._next < stop:
            self._futs[self._next] = self.loader.tpool.submit(self._make, self._next)
            self._next += 1

    def __len__(self) -> int:
        return self.hi - self.lo

    def _make(self, k: int) -> tuple[np.ndarray, np.ndarray | None]:
        """(the scan, its ground returns or None), both in the chunk's world frame."""
        p = self.loader.get(self.lo + k)
        t0 = time.perf_counter()
        if p is None:
            return np.zeros((0, 3), np.float32), None  # keeps the time offsets of the others right
        T = p.to_world.copy()
        T[:3, 3] -= self.anchor
        s = transform_points(p.kept, T)
        g = None if p.ground is None else transform_points(p.ground, T)
        self.loader.stages.add("transform", time.perf_counter() - t0)
        return s, g

    def _scan(self, k: int) -> np.ndarray:
        return self._made(k)[0]

    def ground(self, k: int) -> np.ndarray | None:
        """Ground returns of item ``k`` in the chunk's world frame (None unless the loader keeps them)."""
        return self._made(k)[1]

    def _made(self, k: int):
        self._advance(k)
        fut = self._futs.get(k)
        if fut is None:  # dropped (asked for again after its window passed): make it again
            fut = self._futs[k] = self.loader.tpool.submit(self._make, k)
        if not fut.done():
            t0 = time.perf_counter()
            fut.result()
            self.loader.stages.waited(time.perf_counter() - t0)
        return fut.result()

    def __getitem__(self, k):
        if isinstance(k, slice):
            idx = range(len(self))[k]
            if k.step in (None, 1) and len(idx):  # a window: nothing before it is asked for again
                for j in [j for j in self._futs if j < idx[0]]:
                    del self._futs[j]
            return [self._scan(j) for j in idx]
        k = int(k)
        if k < 0:
            k += len(self)
        if not 0 <= k < len(self):
            raise IndexError(k)
        return self._scan(k)

    def sensor(self, k: int) -> np.ndarray | None:
        """Sensor position of item ``k`` in the chunk's world frame (None where unknown)."""
        p = self.loader.get(self.lo + k)
        return None if p is None or p.sensor is None else p.sensor - self.anchor

    def close(self) -> None:
        for f in self._futs.values():
            f.cancel()
        self._futs.clear()


class ScanFieldView(Sequence):
    """One per-scan field (``FIELD(k)``) of a scan sequence that has it (ChunkScans, StreamScans),
    as a sequence of its own: what the methods that take it get (``sensors=``, ``ground=``)."""

    FIELD = ""

    def __init__(self, scans) -> None:
        self.scans = scans

    def __len__(self) -> int:
        return len(self.scans)

    def __getitem__(self, k):
        get = getattr(self.scans, self.FIELD)
        if isinstance(k, slice):
            return [get(j) for j in range(len(self))[k]]
        return get(int(k))


class SensorView(ScanFieldView):
    """Each scan's sensor position (``sensors=``)."""

    FIELD = "sensor"


class GroundView(ScanFieldView):
    """Each scan's ground returns, where the loader keeps them (``ground=``)."""

    FIELD = "ground"
