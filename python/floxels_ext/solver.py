"""Driving ``floxels::solver_run``: the whole optimisation without per-iteration host work.

On the CPU the op runs every iteration itself and returns when all problems have stopped.
On CUDA the iterations are enqueued in chunks; each chunk is replayed from a CUDA graph
(captured once per call group, after a first eager chunk has loaded the kernels). The host
only looks at the problems' "active" flags once per chunk, one chunk behind the GPU (the
next chunk is already queued), so the GPU never waits for the host; chunks enqueued after
every problem stopped are no-ops.
"""

from __future__ import annotations

import os

import torch

from .ops.solver import COL_ACTIVE, PackedProblems

DEFAULT_CHUNK = 50


def graphs_enabled() -> bool:
    """CUDA graphs are used unless FLOXELS_CUDA_GRAPHS=0 (for debugging and comparisons)."""
    return os.environ.get("FLOXELS_CUDA_GRAPHS", "1") != "0"


def run_solver(packed: PackedProblems, chunk: int = DEFAULT_CHUNK, use_graph: bool | None = None) -> None:
    """Run ``packed`` until every problem has stopped (at most ``cfg.max_iters`` iterations)."""
    max_iters = packed.cfg.max_iters
    if not packed.points.is_cuda:
        packed.run(max_iters)
        return
    use_graph = graphs_enabled() if use_graph is None else use_graph
    chunk = max(1, min(chunk, max_iters))
    stream = torch.cuda.current_stream()
    flags = [torch.empty(packed.num_problems, dtype=torch.float64, pin_memory=True) for _ in range(2)]
    pending: list[tuple[torch.cuda.Event, torch.Tensor]] = []
    graph = None
    done = 0
    k = 0
    while done < max_iters:
        n = min(chunk, max_iters - done)
        if graph is None and use_graph and done > 0 and n == chunk:
            graph = _capture(packed, chunk)
        if graph is not None and n == chunk:
            graph.replay()
        else:
            packed.run(n)
        done += n
        buf = flags[k % 2]
        k += 1
        buf.copy_(packed.state[:, COL_ACTIVE], non_blocking=True)
        ev = torch.cuda.Event()
        ev.record(stream)
        pending.append((ev, buf))
        if len(pending) > 1:  # look one chunk behind: the chunk just queued keeps the GPU busy
            ev0, buf0 = pending.pop(0)
            ev0.synchronize()
            if not bool(buf0.any()):
                break
    torch.cuda.current_stream().synchronize()


def _capture(packed: PackedProblems, n: int) -> torch.cuda.CUDAGraph:
    # Capture on a side stream (the legacy default stream cannot be captured). Not
    # torch.cuda.graph(): its gc.collect() and empty_cache() would cost more than a frame.
    graph = torch.cuda.CUDAGraph()
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        graph.capture_begin()
        try:
            packed.run(n)
        finally:
            graph.capture_end()
    torch.cuda.current_stream().wait_stream(side)
    return graph
