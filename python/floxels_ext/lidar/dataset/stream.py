"""The engine of ``floxels run``: the frames of one sequence or of many through one pipeline
(here, or in a Ray worker).

Every run is a stream of tasks (``tasks.Task``: a sequence's frames, opened by
``sequence.open_sequence`` as a :class:`SeqJob`); ``floxels run SEQ`` is a stream of one. One
set of reader threads, transform threads and writers serves every sequence, and the method gets
one stream of targets (:func:`floxels_ext.estimator.windows.estimate_stream`): the segments
of successive sequences laid end to end in one index space. Running a dataset as one run per
sequence had started and drained everything per sequence: reader and writer threads, the
read-ahead (the device waited for the first frames), the method's own pipeline (its first batch
prepared with the device idle, its last optimised with nothing beside it) and the writers' tail.

* A segment is one chunk of one sequence (``layout.plan_chunks``: ``--chunk`` targets and
  their support scans, moved into one world frame re-centred on the chunk's first readable
  frame), so every window, anchor and flow is the same however the frames are cut into tasks;
  windows never leave their segment, so no window mixes frames of two sequences, while a batch
  of the optimiser may hold targets of both sides of a sequence end (``layout``: the segments,
  the scans, the targets).
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

import sys
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from floxels_ext.lidar.dataset.layout import Layout, StreamScans, Targets
from floxels_ext.lidar.dataset.scan_views import GroundView, SegmentView, SensorView
from floxels_ext.lidar.pipeline.frame_checks import frame_failure
from floxels_ext.lidar.pipeline.frame_loader import FrameLoader
from floxels_ext.methods import accepts

__all__ = ["SeqJob", "Ahead", "run_stream", "EstimationError", "GIL_SWITCH_INTERVAL"]

# Python hands the GIL to a waiting thread only every "switch interval" (5 ms by default): with
# reader and writer threads holding it for numpy work, the thread driving the GPU waited that
# long each time it gave it up around a device call. A shorter interval during the run lets it
# back sooner (bench/RESULTS.md, floxels run section); None leaves Python's setting alone.
GIL_SWITCH_INTERVAL: float | None = 0.0005


class EstimationError(ValueError):
    """The method rejected its input before any frame was done (bad options, bad scans)."""


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


def run_stream(source: Iterator[SeqJob], *, writer, method, num_scans: int, chunk: int | None, device,
               options: dict, stages, on_frame_done: Callable[[SeqJob, int], None],
               on_finish: Callable[[SeqJob], None], report: Callable[[str], None]) -> None:
    """Estimate every target of every job of ``source`` through one pipeline (module docstring).

    ``on_frame_done(job, i)`` when frame ``i`` is written or failed; ``on_finish(job)`` once a
    job is done (also a job with nothing to do), on whichever thread finished it; its loader has
    dropped its frames then (``release``) and is closed before returning. The writer is
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
            job.loader.release()
            on_finish(job)

    def finish_empty(job: SeqJob) -> None:
        job.done = True
        job.t_end = time.perf_counter()
        job.loader.release()
        on_finish(job)

    layout = Layout(src, num_scans, chunk, finish_empty)
    scans = StreamScans(layout, stages)
    delivered: set[int] = set()

    def deliver(g: int, flow, fields=None) -> None:
        now = time.perf_counter()
        dt, state["t_last"] = now - state["t_last"], now
        seg, i = layout.locate(g)
        job = seg.job
        delivered.add(g)
        p = job.loader.get(i)
        why = None if p is None else frame_failure(method, options, job.loader, i, len(job.seq), fields)
        if p is None or why is not None:
            resolve(job, i, why or job.loader.errors.get(i, "unreadable"))
        else:
            if not job.times:  # its wall time starts when the stream starts working on it
                job.t_start = now - dt
            job.times.append(dt)
            flow = np.asarray(flow, np.float32).reshape(-1, 3)
            writer.put(i, p, flow, dt, job.next_pose(i), fields, write_one=job.write_one,
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
        targets = Targets(layout, lambda job, i, msg: resolve(job, i, msg))
        stream = getattr(method, "estimate_stream", None)
        while True:
            t0 = time.perf_counter()
            stages.in_estimate = True
            try:
                if stream is not None:
                    extra = {"sensors": SensorView(scans)} if accepts(stream, "sensors") else {}
                    if method.wants_ground(options) and accepts(stream, "ground"):
                        extra["ground"] = GroundView(scans)
                    stream(scans, targets, device, dict(options), deliver, **extra)
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


def _per_segment(method, scans: StreamScans, targets: Targets, device, options: dict, deliver) -> None:
    """A method without ``estimate_stream``: one ``estimate_sequence`` call per segment (it
    starts and drains its pipeline per chunk)."""
    pass_times = accepts(method.estimate_sequence, "times")
    pass_sensors = accepts(method.estimate_sequence, "sensors")
    pass_ground = method.wants_ground(options)
    batch: list = []
    seg_now = None

    def flush():
        if not batch:
            return
        seg = seg_now
        view = SegmentView(scans, seg.lo, seg.hi)
        extra = {"times": list(seg.times)} if pass_times and seg.times is not None else {}
        if pass_sensors:
            extra["sensors"] = SensorView(view)
        if pass_ground:
            extra["ground"] = GroundView(view)
        method.estimate_sequence(view, [g - seg.lo for g in batch], device, dict(options),
                                 lambda f, flow, fields=None, lo=seg.lo: deliver(lo + int(f), flow, fields), **extra)
        batch.clear()

    for g, seg in targets:
        if seg is not seg_now and batch:
            targets.unissue(g)  # the next segment's first target waits until this one is done
            flush()
            continue
        seg_now = seg
        batch.append(g)
    flush()
