"""Driving ``floxels::solver_run``: the whole optimisation without per-iteration host work.

On the CPU the op runs every iteration itself and returns when all problems have stopped.
On CUDA the iterations are enqueued in chunks (one op call enqueues a chunk's kernels, no
Python per iteration). The host only looks at the problems' "active" flags once per chunk,
one chunk behind the GPU (the next chunk is already queued), so the GPU never waits for the
host; chunks enqueued after every problem stopped are cheap no-ops. :class:`SolverRun` can
also be advanced without blocking (:meth:`SolverRun.poll`), which lets the estimator prepare
the next frames on the host while the GPU optimises these.

Where the op uses its persistent loop kernel (``floxels::solver_loop_blocks``: single
frames and small batches, whose point blocks all fit on the GPU at once) one call runs every
iteration in a single cooperative launch that ends by itself once every problem has
stopped, so the default chunk is then the whole run.

(Replaying the chunks from CUDA graphs was measured slower on an H100 and removed: a graph
must be captured and instantiated for every new problem, ~1 ms, while the eager chunk is
already enqueued by one C++ call; bench/RESULTS.md.)
"""

from __future__ import annotations

import torch

from floxels_ext.ops.solver import COL_ACTIVE, PackedProblems

DEFAULT_CHUNK = 50


class SolverRun:
    """The iterations of one :class:`PackedProblems`, enqueued chunk by chunk on the stream
    that is current when the run is created. ``poll()`` tops up the queue without blocking
    (returns False once nothing is left to enqueue); ``finish()`` runs to the end and waits."""

    def __init__(self, packed: PackedProblems, chunk: int | None = None, depth: int = 2) -> None:
        self.packed = packed
        self.max_iters = packed.cfg.max_iters
        self.cuda = packed.points.is_cuda
        if chunk is None:  # one launch for the whole run where the op loops on the device
            chunk = self.max_iters if self.cuda and packed.loop_blocks() > 0 else DEFAULT_CHUNK
        self.chunk = max(1, min(chunk, self.max_iters))
        self.depth = max(1, depth)  # chunks kept queued while polling
        self.done = 0               # iterations enqueued
        self.stopped = False        # every problem has stopped (seen on the host)
        self.pending: list[tuple[torch.cuda.Event, torch.Tensor]] = []
        if self.cuda:
            self.stream = torch.cuda.current_stream(packed.points.device)
            self.flags = [torch.empty(packed.num_problems, dtype=torch.float64, pin_memory=True)
                          for _ in range(self.depth + 1)]
            self.k = 0

    def _enqueue(self) -> None:
        n = min(self.chunk, self.max_iters - self.done)
        with torch.cuda.stream(self.stream):
            self.packed.run(n)
            self.done += n
            buf = self.flags[self.k % len(self.flags)]
            self.k += 1
            buf.copy_(self.packed.state[:, COL_ACTIVE], non_blocking=True)
            ev = torch.cuda.Event()
            ev.record(self.stream)
        self.pending.append((ev, buf))

    def _retire(self, block: bool) -> None:
        """Look at the oldest queued chunk's flags (waiting for it if ``block``)."""
        ev, buf = self.pending[0]
        if not block and not ev.query():
            return
        ev.synchronize()
        self.pending.pop(0)
        if not bool(buf.any()):
            self.stopped = True

    def poll(self) -> bool:
        """Non-blocking: retire finished chunks, keep ``depth`` chunks queued."""
        if not self.cuda:
            return False
        while self.pending and not self.stopped:
            before = len(self.pending)
            self._retire(block=False)
            if len(self.pending) == before:
                break
        while not self.stopped and self.done < self.max_iters and len(self.pending) < self.depth:
            self._enqueue()
        return not self.stopped and self.done < self.max_iters

    def finish(self, wait: bool = True) -> None:
        """Run until every problem has stopped (at most ``cfg.max_iters`` iterations).
        ``wait=False``: return once the last iterations are enqueued (the caller queues the
        read-back behind them and synchronises once)."""
        if not self.cuda:
            if self.done == 0:
                self.packed.run(self.max_iters)
                self.done = self.max_iters
            return
        while not self.stopped and self.done < self.max_iters:
            self._enqueue()
            if len(self.pending) > 1:  # look one chunk behind: the chunk just queued keeps the GPU busy
                self._retire(block=True)
        if wait:
            self.wait()

    def wait(self) -> None:
        """Wait for everything queued on the run's stream (its iterations, and what the caller
        queued behind them: the read-backs)."""
        if self.cuda:
            self.stream.synchronize()


def run_solver(packed: PackedProblems, chunk: int | None = None) -> None:
    """Run ``packed`` until every problem has stopped (at most ``cfg.max_iters`` iterations)."""
    SolverRun(packed, chunk).finish()

