"""The frames of many sequences through one ``floxels run`` pipeline (``floxels run DATASET``,
locally or in a Ray worker).

Running a dataset as one plain run per sequence started and drained everything per sequence:
reader and writer threads, the read-ahead (the device waited for the first frames), the
method's own pipeline (its first batch prepared with the device idle, its last optimised
with nothing beside it) and the writers' tail. Here one set of reader threads, transform
threads and writers serves every sequence, and the method gets one stream of targets
(:func:`floxels_ext.estimator.stream.estimate_stream`): the segments of successive sequences
laid end to end in one index space.

* A segment is one chunk of one sequence, exactly as the plain run cuts it
  (:func:`floxels_ext.lidar.pipeline.plan_chunks`: ``--chunk`` targets and their support
  scans, moved into one world frame re-centred on the chunk's first readable frame), so every
  window, anchor and flow equals the plain run's; windows never leave their segment, so no
  window mixes frames of two sequences, while a batch of the optimiser may hold targets of
  both sides of a sequence end.
* Sequences are opened (files listed, poses, resume) one ahead on a thread of their own
  (``source``: an iterator of :class:`SeqJob`, :class:`Ahead`), and the read-ahead runs
  across sequence ends: the next sequence's first frames are read while the method still
  works on the current one.
* Each sequence keeps its own outputs, resume and failures: a frame that cannot be read or
  written fails alone; an error of the method fails the targets it had been given and not
  yet returned, and the stream goes on with the next ones. A sequence is finished
  (``on_finish``: its summary) once each of its targets is written or failed.
"""

from __future__ import annotations

import bisect
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from floxels_ext.lidar.frame_loader import FrameLoader
from floxels_ext.lidar.pipeline import GIL_SWITCH_INTERVAL, READ_AHEAD, EstimationError, plan_chunks, snap_anchor
from floxels_ext.lidar.preprocess import transform_points

__all__ = ["SeqJob", "Ahead", "run_stream"]

TRANSFORM_AHEAD = 32  # as ChunkScans: two batches of windows, so the method prepares the next batch early


@dataclass
class SeqJob:
    """One sequence (or frame range of one) in the stream: what to estimate and where it goes."""

    label: str                  # for messages: the input (and frame range)
    seq: object                 # the sequence (``io.sources``): frames and their names
    loader: FrameLoader         # its reader (sharing the stream's pools)
    todo: list[int]             # sorted frame indices to estimate
    write_one: Callable         # FrameOutput: one frame to its .npz
    next_pose: Callable         # i -> the next frame's pose (ego_motion) or None
    times_s: list | None = None  # per-frame times (s) where the input names them
    info: dict = field(default_factory=dict)   # whatever the opener wants back at on_finish
    failed: dict = field(default_factory=dict)  # frame -> message
    times: list = field(default_factory=list)   # s per delivered frame
    written: int = 0
    left: int = 0               # targets not yet written or failed
    t_start: float = 0.0
    t_end: float = 0.0
    done: bool = False

    @property
    def n(self) -> int:
        return len(self.seq.frames)


class Ahead:
    """An iterator whose next item is computed on a thread of its own, from when :meth:`start`
    asks for it (the stream asks when its read-ahead nears the end of what it has: opening the
    next sequence overlaps the end of this one, and a Ray worker leases its next task only
    then, so the last tasks of a job are spread over the workers). ``ready()``: whether the
    next item is there (never waits)."""

    _END = object()

    def __init__(self, items: Iterator) -> None:
        self._it = iter(items)
        self._ex = ThreadPoolExecutor(max_workers=1, thread_name_prefix="floxels-open")
        self._next = None
        self._lock = threading.Lock()

    def start(self) -> None:
        with self._lock:
            if self._next is None:
                self._next = self._ex.submit(next, self._it, self._END)

    def ready(self) -> bool:
        return self._next is not None and self._next.done()

    def __iter__(self):
        return self

    def __next__(self):
        self.start()
        item = self._next.result()
        with self._lock:
            self._next = None
        if item is self._END:
            raise StopIteration
        return item

    def close(self) -> None:
        if self._next is not None:
            self._next.cancel()
        self._ex.shutdown(wait=True, cancel_futures=True)


class _Seg:
    """One chunk of one job: frames ``[lo, hi)`` at stream indices ``[g, g + hi - lo)``."""

    def __init__(self, job: SeqJob, lo: int, hi: int, g: int, targets: list[int], num_scans: int) -> None:
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
                        a = snap_anchor(p.to_world[:3, 3])
                        break
                self._anchor.append(a)
            return self._anchor[0]


class _Layout:
    """The stream's segments so far; pulls jobs from ``source`` as targets or read-ahead need them."""

    def __init__(self, source: Ahead, num_scans: int, chunk: int | None, on_empty: Callable) -> None:
        self.source, self.num_scans, self.chunk, self.on_empty = source, num_scans, chunk, on_empty
        self.segs: list[_Seg] = []
        self.starts: list[int] = []
        self.end = 0
        self.exhausted = False
        self.jobs: list[SeqJob] = []
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
                    self.segs.append(_Seg(job, lo, hi, self.end, c, self.num_scans))
                    self.starts.append(self.end)
                    self.end += hi - lo
                return True
            return False

    def locate(self, g: int) -> tuple[_Seg, int]:
        """(segment, frame index in its sequence) of stream index ``g``."""
        k = bisect.bisect_right(self.starts, g) - 1
        seg = self.segs[k]
        return seg, seg.lo + g - seg.g


class _StreamScans(Sequence):
    """The stream's scans for the method: item ``g`` is its frame's kept points in its chunk's
    world frame, transformed on the loaders' transform threads ``TRANSFORM_AHEAD`` items ahead
    of the one asked for, with the frames read ``READ_AHEAD`` ahead (into the next sequence)."""

    def __init__(self, layout: _Layout, tpool, stages) -> None:
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

    def _make(self, g: int) -> np.ndarray:
        seg, i = self.layout.locate(g)
        p = seg.job.loader.get(i)
        t0 = time.perf_counter()
        anchor = seg.anchor()
        if p is None or anchor is None:
            return np.zeros((0, 3), np.float32)  # keeps the time offsets of the others right
        T = p.to_world.copy()
        T[:3, 3] -= anchor
        s = transform_points(p.kept, T)
        self.stages.add("transform", time.perf_counter() - t0)
        return s

    def _scan(self, g: int) -> np.ndarray:
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


class _Targets:
    """The method's targets, ``(stream index, Segment)`` in order, pulling sequences as it goes;
    a chunk without a readable frame fails its targets here (as the plain run). A new iterator
    after an error goes on after the targets already issued."""

    def __init__(self, layout: _Layout, fail: Callable) -> None:
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


def _accepts_times(fn) -> bool:
    import inspect

    try:
        return "times" in inspect.signature(fn).parameters
    except (TypeError, ValueError):
        return False


def run_stream(source: Iterator[SeqJob], *, writer, method, num_scans: int, chunk: int | None, device,
               options: dict, stages, tpool, on_frame_done: Callable[[SeqJob, int], None],
               on_finish: Callable[[SeqJob], None], report: Callable[[str], None]) -> None:
    """Estimate every target of every job of ``source`` through one pipeline (module docstring).

    ``on_frame_done(job, i)`` when frame ``i`` is written or failed; ``on_finish(job)`` once a
    job is done (also a job with nothing to do), on whichever thread finished it. The writer is
    closed (queued results written) before returning, also on errors and Ctrl-C. Raises
    ``EstimationError`` (a ValueError/TypeError of the method before any frame was delivered)."""
    pad = num_scans - 1
    lock = threading.Lock()
    state = {"delivered": 0, "t_last": time.perf_counter()}
    src = source if isinstance(source, Ahead) else Ahead(source)

    def resolve(job: SeqJob, i: int, error: str | None) -> None:
        with lock:
            if error is not None:
                job.failed[i] = error
            else:
                job.written += 1
            job.left -= 1
            finished = job.left == 0 and not job.done
            job.done |= finished
        on_frame_done(job, i)
        if finished:
            job.t_end = time.perf_counter()
            job.loader.close()
            on_finish(job)

    def finish_empty(job: SeqJob) -> None:
        job.done = True
        job.t_end = time.perf_counter()
        job.loader.close()
        on_finish(job)

    layout = _Layout(src, num_scans, chunk, finish_empty)
    scans = _StreamScans(layout, tpool, stages)
    delivered: set[int] = set()

    def deliver(g: int, flow) -> None:
        now = time.perf_counter()
        dt, state["t_last"] = now - state["t_last"], now
        seg, i = layout.locate(g)
        job = seg.job
        delivered.add(g)
        p = job.loader.get(i)
        if p is None:
            resolve(job, i, job.loader.errors.get(i, "unreadable"))
        else:
            if not job.times:  # its wall time starts when the stream starts working on it
                job.t_start = now - dt
            job.times.append(dt)
            flow = np.asarray(flow, np.float32).reshape(-1, 3)
            writer.put(i, p, flow, dt, job.next_pose(i), write_one=job.write_one,
                       on_done=lambda i, err, job=job: resolve(job, i, err))
            state["delivered"] += 1
        job.loader.evict_below(i - pad)  # frames before this window: no later window reads them
        stages.add("deliver", time.perf_counter() - now)

    old_interval = sys.getswitchinterval()
    if GIL_SWITCH_INTERVAL is not None:
        sys.setswitchinterval(min(old_interval, GIL_SWITCH_INTERVAL))
    t_start = time.perf_counter()
    stages.optimiser_thread = threading.get_ident()
    try:
        targets = _Targets(layout, lambda job, i, msg: resolve(job, i, msg))
        stream = getattr(method, "estimate_stream", None)
        while True:
            t0 = time.perf_counter()
            stages.in_estimate = True
            try:
                if stream is not None:
                    stream(scans, targets, device, dict(options), deliver)
                else:
                    _per_segment(method, scans, targets, device, options, deliver)
                break
            except (ValueError, TypeError, RuntimeError) as e:
                if isinstance(e, (ValueError, TypeError)) and state["delivered"] == 0 and \
                        not any(j.failed for j in layout.jobs):
                    raise EstimationError(str(e)) from None
                # e.g. out of GPU memory: the targets in flight fail, the stream goes on after them
                lost = [g for g in targets.issued if g not in delivered]
                for g in lost:
                    seg, i = layout.locate(g)
                    resolve(seg.job, i, seg.job.loader.errors.get(i) or f"estimation failed: {e}")
                if lost:
                    first, last = layout.locate(lost[0]), layout.locate(lost[-1])
                    report(f"floxels: error: frames {first[0].job.seq.frames[first[1]].name}.."
                           f"{last[0].job.seq.frames[last[1]].name} ({first[0].job.label}): {e}")
                targets.issued = []  # the next call goes on after them
            finally:
                stages.in_estimate = False
                stages.add("estimate", time.perf_counter() - t0)
    finally:
        scans.close()
        writer.close()  # results already computed are written, also on Ctrl-C
        src.close()
        for job in layout.jobs:
            job.loader.close()
        sys.setswitchinterval(old_interval)
        stages.add("wall", time.perf_counter() - t_start)


def _per_segment(method, scans: _StreamScans, targets: _Targets, device, options: dict, deliver) -> None:
    """A method without ``estimate_stream``: one ``estimate_sequence`` call per segment (it
    starts and drains its pipeline per chunk, as the plain run does)."""
    pass_times = _accepts_times(method.estimate_sequence)
    batch: list = []
    seg_now = None

    def flush():
        if not batch:
            return
        seg = seg_now
        view = _SegmentView(scans, seg.lo, seg.hi)
        extra = {"times": list(seg.times)} if pass_times and seg.times is not None else {}
        method.estimate_sequence(view, [g - seg.lo for g in batch], device, dict(options),
                                 lambda f, flow, lo=seg.lo: deliver(lo + int(f), flow), **extra)
        batch.clear()

    for g, seg in targets:
        if seg is not seg_now and batch:
            targets.unissue(g)  # the next segment's first target waits until this one is done
            flush()
            continue
        seg_now = seg
        batch.append(g)
    flush()


class _SegmentView(Sequence):
    """Stream scans ``[lo, hi)`` as a sequence of their own (for ``estimate_sequence``)."""

    def __init__(self, scans: _StreamScans, lo: int, hi: int) -> None:
        self.scans, self.lo, self.hi = scans, lo, hi

    def __len__(self) -> int:
        return self.hi - self.lo

    def __getitem__(self, k):
        if isinstance(k, slice):
            idx = range(len(self))[k]
            if k.step in (None, 1) and len(idx):
                return self.scans[self.lo + idx[0]:self.lo + idx[-1] + 1]
            return [self.scans[self.lo + j] for j in idx]
        k = int(k)
        if k < 0:
            k += len(self)
        if not 0 <= k < len(self):
            raise IndexError(k)
        return self.scans[self.lo + k]
