"""Writing ``floxels run``'s outputs: :class:`FrameOutput` turns one estimated frame into its
``.npz`` (layout: :data:`floxels_ext.lidar.io.outputs.OUTPUT`), :class:`WriterPool` runs it on
writer threads or processes while the optimiser goes on.

Threads by default: an output is written in a few ms, mostly without the GIL (the flow math in
one op, the ``.npz`` written directly: :func:`floxels_ext.lidar.io.outputs.write_output`), and
writer processes (``--worker-kind process``: a GIL of their own, each frame pickled across as
~1.5 MB) were slower on the hosts measured (bench/RESULTS.md). Outputs are identical either way.
"""

from __future__ import annotations

import dataclasses
import queue
import threading
import time
from pathlib import Path

import numpy as np

from floxels_ext.lidar.io.outputs import write_output

__all__ = ["FrameOutput", "WriterPool", "DRAIN_WRITERS"]

# Threads writing what is still queued when the run ends (``floxels run``: at most this many
# and the cores it may use): the method is done then and the cores are free, while the run
# waits for those writes (the last batch's frames; more writers during the run only slowed
# the method, bench/RESULTS.md).
DRAIN_WRITERS = 8


@dataclasses.dataclass
class FrameOutput:
    """Everything a frame's output needs besides the frame: paths, the run's metadata."""

    out_path: dict[int, Path]
    sources: dict[int, str]
    stamps: list
    meta: dict
    dynamic_threshold: float
    compress: bool = False
    self_contained: bool = False
    inputs: dict[int, str] = dataclasses.field(default_factory=dict)  # frame -> its inputs record (JSON)

    def __call__(self, i: int, p, flow_kept: np.ndarray, elapsed: float, next_to_world, fields=None) -> None:
        import torch

        from floxels_ext.ops.lidar import frame_flow

        # world-axes flow -> the frame's rows and native axes (f @ R), dynamic flags: one op,
        # float32, without the GIL (in numpy this held it for ~3 ms a frame)
        full, dynamic = frame_flow(torch.from_numpy(np.ascontiguousarray(flow_kept, np.float32)),
                                   torch.from_numpy(p.mask), torch.from_numpy(p.nonfinite),
                                   torch.from_numpy(p.to_world[:3, :3].astype(np.float32)), self.dynamic_threshold)
        extra = {}
        if next_to_world is not None:
            extra["ego_motion"] = np.linalg.solve(next_to_world, p.to_world)
        if self.self_contained:
            extra["points"] = p.points
        if p.crc is not None:
            extra["source_crc32"] = np.int64(p.crc)
        if self.stamps[i] is not None:
            extra["timestamp_ns"] = np.int64(self.stamps[i])
        if i in self.inputs:
            extra["inputs"] = np.str_(self.inputs[i])
        if fields is not None:  # the motion evidence of the kept rows -> every row of the file
            extra.update(evidence_rows(p.mask, fields))
        write_output(self.out_path[i], compress=self.compress, flow=full.numpy(), mask=p.mask,
                     dynamic=dynamic.numpy(), pose=p.to_world, elapsed_s=np.float64(elapsed),
                     source=np.str_(self.sources[i]), **self.meta, **extra)


def evidence_rows(mask: np.ndarray, fields: dict) -> dict:
    """``evidence`` (float32, NaN on rows not optimised) and ``explained`` (bool, False there)
    over all rows of a frame file, from the values of its ``mask`` rows (the method's order)."""
    n = len(mask)
    score = np.full(n, np.nan, np.float32)
    score[mask] = np.asarray(fields["evidence"], np.float32).reshape(-1)
    explained = np.zeros(n, bool)
    explained[mask] = np.asarray(fields["explained"], bool).reshape(-1)
    return {"evidence": score, "explained": explained}


_CHILD: dict = {}


def _child_init(write_one) -> None:
    _CHILD["write"] = write_one


def _child_write(item, write_one=None) -> float:
    t0 = time.perf_counter()
    (write_one or _CHILD["write"])(*item)
    return time.perf_counter() - t0


class WriterPool:
    """Writes results on ``workers`` threads (``kind="thread"``) or forked processes
    (``"process"``); ``put`` blocks while ``depth`` results wait (flat memory). Frames are
    independent files, written atomically, so their order does not matter; a failed write
    fails its frame (``failures``), not the run. Processes start at construction
    (:mod:`floxels_ext.lidar.pipeline.worker_processes`). The sequences of a run share one pool:
    each ``put`` names its sequence's ``write_one`` (``write_one`` given here: the one the
    processes hold) and an ``on_done(i, error)`` callback (on a writer thread; ``error`` None
    when written)."""

    def __init__(self, write_one, stages, *, depth: int = 32, workers: int = 4, kind: str = "thread",
                 drain: int | None = None) -> None:
        self.write_one, self.stages, self.kind = write_one, stages, kind
        self.failures: dict[int, str] = {}
        self.written = 0
        self._lock = threading.Lock()
        workers = max(1, workers)
        self.drain = max(workers, drain or 0)  # threads writing what is queued at close
        if kind == "process":
            from floxels_ext.lidar.pipeline.worker_processes import process_pool

            self._slots = threading.BoundedSemaphore(depth)
            self.pool = process_pool(workers, _child_init, (write_one,))
        else:
            self.q: queue.Queue = queue.Queue(maxsize=depth)
            self.threads = [threading.Thread(target=self._loop, name=f"floxels-write-{k}", daemon=True)
                            for k in range(workers)]
            for t in self.threads:
                t.start()

    def put(self, i: int, p, flow_kept, elapsed: float, next_to_world, fields=None, *, write_one=None,
            on_done=None) -> None:
        t0 = time.perf_counter()
        if self.kind == "process":
            self._slots.acquire()
            self.stages.add("wait_writer", time.perf_counter() - t0)
            light = dataclasses.replace(p, kept=np.zeros((0, 3), np.float32))  # the writer needs no kept points
            if write_one is self.write_one:  # the children hold it from their start: not sent with each frame
                write_one = None
            try:
                fut = self.pool.submit(_child_write, (i, light, flow_kept, elapsed, next_to_world, fields), write_one)
            except Exception as e:  # a writer died (killed, out of memory): the pool is broken
                self._slots.release()
                with self._lock:
                    self.failures[i] = f"cannot write the output: {e}"
                if on_done is not None:
                    on_done(i, self.failures[i])
                return
            fut.add_done_callback(lambda f, i=i: self._done(i, f, on_done))
        else:
            self.q.put(((i, p, flow_kept, elapsed, next_to_world, fields), write_one, on_done))
            self.stages.add("wait_writer", time.perf_counter() - t0)

    def _done(self, i: int, fut, on_done=None) -> None:
        err = fut.exception()
        with self._lock:
            if err is None:
                self.written += 1
            else:  # a full disk, a permission problem: this frame fails, not the run
                self.failures[i] = f"cannot write the output: {err}"
        if err is None:
            self.stages.add("write", fut.result())  # seconds the child spent
        self._slots.release()
        if on_done is not None:
            on_done(i, None if err is None else f"cannot write the output: {err}")

    def _loop(self) -> None:
        while True:
            entry = self.q.get()
            if entry is None:
                return
            item, write_one, on_done = entry
            t0 = time.perf_counter()
            error = None
            try:
                (write_one or self.write_one)(*item)
                with self._lock:
                    self.written += 1
            except Exception as e:  # a full disk, a permission problem: this frame fails, not the run
                error = f"cannot write the output: {e}"
                with self._lock:
                    self.failures[item[0]] = error
            self.stages.add("write", time.perf_counter() - t0)
            if on_done is not None:
                on_done(item[0], error)

    def close(self) -> None:
        """Write what is queued (finished results are not thrown away; on up to ``drain``
        threads), then stop."""
        if self.kind == "process":
            self.pool.shutdown(wait=True)
            return
        extra = min(self.q.qsize(), self.drain - len(self.threads))
        for k in range(extra):
            t = threading.Thread(target=self._loop, name=f"floxels-write-{len(self.threads)}", daemon=True)
            t.start()
            self.threads.append(t)
        for _ in self.threads:
            self.q.put(None)
        for t in self.threads:
            t.join()
