"""The index space of a dataset stream (``stream``): the chunks of successive sequences
laid end to end as segments (:class:`Layout`), the method's scans over it (:class:`StreamScans`:
read and transformed ahead, across sequence ends) and its targets (:class:`Targets`).

A segment is one chunk of one sequence exactly as the plain run cuts it (``--chunk`` targets
and their support scans, in one world frame re-centred on the chunk's first readable frame), so
every window and anchor equals the plain run's.
"""

from __future__ import annotations

import bisect
import threading
import time
from collections.abc import Callable, Sequence

import numpy as np

from floxels_ext.lidar.pipeline.estimate_loop import READ_AHEAD, chunk_anchor, plan_chunks
from floxels_ext.lidar.preprocess.transform import transform_points

__all__ = ["Layout", "StreamScans", "Targets", "TRANSFORM_AHEAD"]

TRANSFORM_AHEAD = 32  # as ChunkScans: two batches of windows, so the method prepares the next batch early


class Segment:
    """One chunk of one job (``stream.SeqJob``): frames ``[lo, hi)`` at stream indices
    ``[g, g + hi - lo)``; ``segment`` is the method's view of it."""

    def __init__(self, job, lo: int, hi: int, g: int, targets: list[int], num_scans: int) -> None:
        from floxels_ext.estimator.stream import Segment

        self.job, self.lo, self.hi, self.g, self.targets = job, lo, hi, g, targets
        times = None if job.times_s is None else job.times_s[lo:hi]
        self.segment = Segment(g, g + hi - lo, times)
        self._anchor: list = []
        self._lock = threading.Lock()

    def anchor(self):
        """The chunk's world-frame origin: its first readable frame's position on the anchor
        grid (as the plain run), None when no frame of it is readable; waits for the reads."""
        with self._lock:
            if not self._anchor:
                a = None
                for i in range(self.lo, self.hi):
                    p = self.job.loader.get(i)
                    if p is not None:
                        a = chunk_anchor(p)
                        break
                self._anchor.append(a)
            return self._anchor[0]


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
                for c in plan_chunks(job.todo, self.chunk):
                    lo, hi = max(0, c[0] - pad), min(job.n, c[-1] + pad + 1)
                    self.segs.append(Segment(job, lo, hi, self.end, c, self.num_scans))
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

    def __init__(self, layout: Layout, tpool, stages) -> None:
        self.layout, self.tpool, self.stages = layout, tpool, stages
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
            self._futs[self._next] = self.tpool.submit(self._make, self._next)
            self._next += 1

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
            fut = self._futs[g] = self.tpool.submit(self._make, g)
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
    a chunk without a readable frame fails its targets here (as the plain run). A new iterator
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
