"""The index space of ``floxels run``'s stream (``stream``): the chunks of successive sequences
laid end to end as segments (:class:`Layout`), the method's scans over it (:class:`StreamScans`:
read and transformed ahead, across sequence ends) and its targets (:class:`Targets`).

A segment is one chunk of one sequence: ``--chunk`` targets (:func:`plan_chunks`) and their
support scans, in one world frame re-centred near a frame fixed by the chunk's place in its
sequence (:class:`Segment`: the first readable frame of its block of ``--chunk`` frames,
counted from the run's first selected frame, support scans before it included), so every
window and anchor is the same whichever way the frames are cut into tasks (a whole sequence,
a resumed run, an engine's or a Ray task, a task halved at a job's end). The anchor is all
that a chunk shares: the same targets grouped otherwise give the same bytes.
"""

from __future__ import annotations

import bisect
import threading
import time
from collections.abc import Callable, Sequence

import numpy as np

from floxels_ext.lidar.preprocess.transform import transform_points

__all__ = ["Layout", "StreamScans", "Targets", "DEFAULT_CHUNK", "READ_AHEAD", "TRANSFORM_AHEAD", "ANCHOR_GRID",
           "snap_anchor", "chunk_anchor", "plan_chunks", "block_start"]

# Targets per method call by default. Long calls: each call starts and drains the method's
# pipeline (estimate_sequence prepares the next batch while the device optimises one), which cost
# ~3 ms a frame with calls of 8-64 frames on an H100 (bench/RESULTS.md). The bound: each call has
# one world frame re-centred on its first frame, and 128 frames (12.8 s at 10 Hz, < 400 m at
# 30 m/s) keep float32 coordinates within ~3e-5 m of exact.
DEFAULT_CHUNK = 128
# Frames read (and preprocessed) ahead of the scan the method asks for: memory stays flat
# whatever the chunk, and the method never waits on a sequence the readers outpace.
READ_AHEAD = 64
# Scans moved into their chunk's world frame ahead of the one asked for: two batches of windows,
# so the method prepares the next batch early.
TRANSFORM_AHEAD = 32

# Each chunk's world frame is re-centred on a point of this grid (m) near its first frame. Why a
# grid: Floxels' voxel and distance-transform grids are aligned to the coordinates, so a shift by
# anything but a multiple of their cells (0.5 m, 0.1 m) changes the estimate (by up to the
# flow itself after a few iterations), and the flow of a frame would depend on where its chunk
# started: on --chunk, --frames, a resumed run or a Ray task's split. 10 m is a multiple of
# every cell size of 0.1, 0.2, 0.25, 0.5, 1, 2, 2.5 or 5 m.
ANCHOR_GRID = 10.0


def snap_anchor(position) -> np.ndarray:
    """The world-frame origin of a chunk whose first frame is at ``position`` (3,): the nearest
    multiple of ``ANCHOR_GRID`` (so results do not depend on where chunks start)."""
    return np.round(np.asarray(position, np.float64) / ANCHOR_GRID) * ANCHOR_GRID


# Points more than this far from their native origin (m) are in a world frame already (map
# scale, UTM); their chunk is re-centred near them instead, on a grid of this step (a multiple
# of ANCHOR_GRID, so the alignment argument above holds; coarse, so that the anchor does not
# depend on which points of the scan are looked at).
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


def plan_chunks(todo: list[int], chunk: int | None, origin: int = 0) -> list[list[int]]:
    """Targets per segment: those of one block of ``chunk`` frames (None: ``DEFAULT_CHUNK``)
    counted from frame ``origin`` (the run's first selected frame), so that a target's chunk,
    and so its anchor, do not depend on where its task starts or which frames are left to do
    (before: ``chunk`` consecutive targets from the task's first one; a task cut at 64 frames
    or a resumed run re-centred its frames elsewhere: flow up to 2 cm off, bytes differing with
    a Ray job's timing)."""
    out: list[list[int]] = []
    for i in todo:
        if out and block_start(i, chunk, origin) == block_start(out[-1][0], chunk, origin):
            out[-1].append(i)
        else:
            out.append([i])
    return out


def block_start(i: int, chunk: int | None, origin: int = 0) -> int:
    """First frame of the block of ``plan_chunks`` that holds frame ``i``."""
    size = chunk or DEFAULT_CHUNK
    return origin + (i - origin) // size * size


class Segment:
    """One chunk of one job (``stream.SeqJob``): frames ``[lo, hi)`` at stream indices
    ``[g, g + hi - lo)``; ``segment`` is the method's view of it."""

    def __init__(self, job, lo: int, hi: int, g: int, targets: list[int], num_scans: int,
                 anchor_from: int | None = None) -> None:
        from floxels_ext.estimator.windows import Segment

        self.job, self.lo, self.hi, self.g, self.targets = job, lo, hi, g, targets
        # where the anchor frame is looked for: the window start of its block's first target
        # (= lo for a chunk that starts its block, as every chunk of a whole run does)
        self.anchor_from = lo if anchor_from is None else min(lo, anchor_from)
        times = None if job.times_s is None else job.times_s[lo:hi]
        self.segment = Segment(g, g + hi - lo, times)
        self._anchor: list = []
        self._lock = threading.Lock()

    def anchor(self):
        """The chunk's world-frame origin: the position on the anchor grid of the first readable
        frame from ``anchor_from`` on (its block's, whichever task holds it), None when no
        frame of the chunk itself is readable; waits for the reads."""
        with self._lock:
            if not self._anchor:
                loader = self.job.loader
                first = next((i for i in range(self.lo, self.hi) if loader.get(i) is not None), None)
                if first is not None:  # frames of the block before this chunk (another task's)
                    first = next((i for i in range(self.anchor_from, self.lo) if loader.get(i) is not None), first)
                self._anchor.append(None if first is None else chunk_anchor(loader.get(first)))
            return self._anchor[0]


def _origin(job) -> int:
    """The frame the run's chunk blocks count from: its selection's first frame (``--frames``;
    a task's ``selection``), 0 for a job without a task."""
    task = job.info.get("task")
    if task is None:
        return 0
    return (getattr(task, "selection", None) or (task.start, task.stop))[0]


class Layout:
    """The stream's segments so far; pulls jobs from ``source`` as targets or read-ahead need them."""

    def __init__(self, source, num_scans: int, chunk: int | None, on_empty: Callable) -> None:
        self.source, self.num_scans, self.chunk, self.on_empty = source, num_scans, chunk, on_empty
        self.segs: list[Segment] = []
        self.starts: list[int] = []
        self.end = 0
        self.exhausted = False
        self.jobs: list = []
        self._lock = threading.RLock()

    def extend(self, block: bool) -> bool:
        """Adds the next job's segments; False when there is none (now, unless ``block``)."""
        with self._lock:
            while not self.exhausted:
                if not block:
                    self.source.start()
                    if not self.source.ready():
                        return False
                try:
                    job = next(self.source)
                except StopIteration:
                    self.exhausted = True
                    return False
                job.t_start = time.perf_counter()
                job.left = len(job.todo)
                if not job.todo:
                    self.on_empty(job)
                    continue
                self.jobs.append(job)
                pad = self.num_scans - 1
                origin = _origin(job)
                for c in plan_chunks(job.todo, self.chunk, origin):
                    lo, hi = max(0, c[0] - pad), min(job.n, c[-1] + pad + 1)
                    at = max(0, block_start(c[0], self.chunk, origin) - pad)
                    self.segs.append(Segment(job, lo, hi, self.end, c, self.num_scans, anchor_from=at))
                    self.starts.append(self.end)
                    self.end += hi - lo
                return True
            return False

    def locate(self, g: int) -> tuple[Segment, int]:
        """(segment, frame index in its sequence) of stream index ``g``."""
        k = bisect.bisect_right(self.starts, g) - 1
        seg = self.segs[k]
        return seg, seg.lo + g - seg.g


class StreamScans(Sequence):
    """The stream's scans for the method: item ``g`` is its frame's kept points in its chunk's
    world frame, transformed on the loaders' transform threads ``TRANSFORM_AHEAD`` items ahead
    of the one asked for, with the frames read ``READ_AHEAD`` ahead (into the next sequence)."""

    def __init__(self, layout: Layout, stages) -> None:
        self.layout, self.stages = layout, stages
        self._futs: dict = {}
        self._next = 0

    def __len__(self) -> int:
        return self.layout.end

    def _advance(self, g: int) -> None:
        lay = self.layout
        while g + READ_AHEAD > lay.end and lay.extend(block=False):
            pass
        k = bisect.bisect_right(lay.starts, g) - 1
        stop = g + READ_AHEAD
        while k < len(lay.segs) and lay.segs[k].g < stop:
            seg = lay.segs[k]
            a = max(g, seg.g) - seg.g + seg.lo
            b = min(stop, seg.g + seg.hi - seg.lo) - seg.g + seg.lo
            seg.job.loader.prefetch(range(a, b))
            k += 1
        stop = min(lay.end, g + TRANSFORM_AHEAD)
        self._next = max(self._next, g)
        while self._next < stop:
            self._submit(self._next)
            self._next += 1

    def _submit(self, g: int):
        """Item ``g``'s transform on its loader's transform threads (shared by the jobs of a
        dataset, a sequence's own otherwise)."""
        fut = self._futs[g] = self.layout.locate(g)[0].job.loader.tpool.submit(self._make, g)
        return fut

    def _make(self, g: int) -> tuple[np.ndarray, np.ndarray | None]:
        """(the scan, its ground returns or None), both in its chunk's world frame."""
        seg, i = self.layout.locate(g)
        p = seg.job.loader.get(i)
        t0 = time.perf_counter()
        anchor = seg.anchor()
        if p is None or anchor is None:
            return np.zeros((0, 3), np.float32), None  # keeps the time offsets of the others right
        T = p.to_world.copy()
        T[:3, 3] -= anchor
        s = transform_points(p.kept, T)
        ground = None if p.ground is None else transform_points(p.ground, T)
        self.stages.add("transform", time.perf_counter() - t0)
        return s, ground

    def _scan(self, g: int) -> np.ndarray:
        return self._made(g)[0]

    def ground(self, g: int) -> np.ndarray | None:
        """Ground returns of item ``g`` in its chunk's world frame (None unless its loader keeps them)."""
        return self._made(g)[1]

    def _made(self, g: int):
        while g >= self.layout.end and self.layout.extend(block=True):
            pass
        self._advance(g)
        fut = self._futs.get(g)
        if fut is None:  # dropped (asked for again after its window passed): make it again
            fut = self._submit(g)
        if not fut.done():
            t0 = time.perf_counter()
            fut.result()
            self.stages.waited(time.perf_counter() - t0)
        return fut.result()

    def sensor(self, g: int) -> np.ndarray | None:
        """Sensor position of item ``g`` in its chunk's world frame (None where unknown)."""
        seg, i = self.layout.locate(g)
        p = seg.job.loader.get(i)
        anchor = seg.anchor()
        return None if p is None or anchor is None or p.sensor is None else p.sensor - anchor

    def __getitem__(self, k):
        if isinstance(k, slice):
            idx = range(k.start or 0, k.stop, k.step or 1)
            if k.step in (None, 1) and len(idx):  # a window: nothing before it is asked for again
                for j in [j for j in self._futs if j < idx[0]]:
                    del self._futs[j]
            return [self._scan(j) for j in idx]
        return self._scan(int(k))

    def close(self) -> None:
        for f in self._futs.values():
            f.cancel()
        self._futs.clear()


class Targets:
    """The method's targets, ``(stream index, Segment)`` in order, pulling sequences as it goes;
    a chunk without a readable frame fails its targets here. A new iterator
    after an error goes on after the targets already issued."""

    def __init__(self, layout: Layout, fail: Callable) -> None:
        self.layout, self.fail = layout, fail
        self.k = 0      # next segment
        self.j = 0      # next target in it
        self.issued: list[int] = []

    def __iter__(self):
        return self

    def __next__(self):
        lay = self.layout
        while True:
            while self.k >= len(lay.segs):
                if not lay.extend(block=True) and self.k >= len(lay.segs):
                    raise StopIteration
            seg = lay.segs[self.k]
            if self.j == 0 and seg.anchor() is None:  # nothing readable: every target fails with its file's error
                for i in seg.targets:
                    self.fail(seg.job, i, seg.job.loader.errors.get(i, "unreadable"))
                self.k += 1
                continue
            if self.j >= len(seg.targets):
                self.k, self.j = self.k + 1, 0
                continue
            i = seg.targets[self.j]
            self.j += 1
            g = seg.g + i - seg.lo
            self.issued.append(g)
            return g, seg.segment

    def unissue(self, g: int) -> None:
        """Takes back the target just issued (not given to the method): the next call yields it again."""
        assert self.issued and self.issued[-1] == g and self.j > 0
        self.issued.pop()
        self.j -= 1
