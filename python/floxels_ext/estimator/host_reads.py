"""The host's reads of device counts after the optimiser, merged over a group's problems.

The steps after the optimiser (estimator/post.py: the rigid refinement and its spreading) need a
few counts on the host -- how many sample rows, accepted clusters, offered points -- to size their
tensors. On CUDA each read is a synchronisation: the host waits for everything queued before it
(at the first read, the whole optimisation), and the device then idles while the host queues the
next steps. One read per problem and count (six a frame with the ``accurate`` preset) left the
GPU waiting on the host for most of those steps.

So the steps are written as generators (:func:`run_steps`): each ``yield``s the list of 0-d
integer tensors it needs on the host and receives their values; the problems of a group run in
lockstep, and each round is one read for all of them. A problem's computation is unchanged (the
same ops on the same values; only the order in which the problems' work is queued changes), so
the results are the same bits. :func:`rows_where` is boolean indexing with the count already read
(``torch.nonzero_static``: no synchronisation of its own).
"""

from __future__ import annotations

from collections.abc import Generator

import torch

__all__ = ["Steps", "run_steps", "run_one", "rows_where"]

# a problem's steps: yields lists of 0-d integer tensors, receives their values, returns its result
Steps = Generator[list, list, object]


def run_steps(steps: list[Steps]) -> list:
    """The results of ``steps`` (generators, one a problem), run in lockstep: each round reads the
    counts every unfinished one asked for in one host transfer (one synchronisation on CUDA)."""
    results: list = [None] * len(steps)
    asked: dict[int, list] = {}
    for i, g in enumerate(steps):
        try:
            asked[i] = next(g)
        except StopIteration as stop:
            results[i] = stop.value
    while asked:
        values = iter(_read([t for want in asked.values() for t in want]))
        nxt = {}
        for i, want in asked.items():
            try:
                nxt[i] = steps[i].send([next(values) for _ in want])
            except StopIteration as stop:
                results[i] = stop.value
        asked = nxt
    return results


def _read(counts: list[torch.Tensor]) -> list[int]:
    """The values of 0-d integer tensors of one device, in one host transfer."""
    return torch.stack([t.reshape(()).to(torch.int64) for t in counts]).tolist() if counts else []


def run_one(steps: Steps):
    """The result of one problem's ``steps`` (:func:`run_steps` of one)."""
    return run_steps([steps])[0]


def rows_where(mask: torch.Tensor, count: int) -> torch.Tensor:
    """(count,) int64 indices of the true entries of the 1-d ``mask``, in order: the rows of
    ``x[mask]`` (``torch.nonzero(mask).squeeze(1)``) where their number ``count`` has been read."""
    if count == 0:
        return torch.zeros(0, dtype=torch.int64, device=mask.device)
    return torch.nonzero_static(mask, size=count).squeeze(1)
