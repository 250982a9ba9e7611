"""How much of a task the Ray driver hands out near a job's end, so that the workers end together.

A worker's pipeline asks for its next task while it still holds frames of the one it runs (its
read-ahead), and the workers run at different rates (two or three share a GPU; the GPUs and
their hosts differ). Near the end of a job, then, they hold different amounts of work, and the
job waits for the one that holds the most. Halving the tasks handed out while the queue is
shorter than the job's workers (the rule before) only makes the last tasks smaller. Here the
driver gives each worker its share of the work left instead. It knows every worker's frames
written (its polls), the frames each still holds and the frames queued, so a worker's share is
``(queued + held by all) / (the workers' summed rate) x its rate - what it holds``: the frames
it can do before the balanced end. A task longer than that is cut there, and the rest is
queued first (``tasks.halve_task(first=...)``).

Near the very end (fewer tasks queued than workers) a task is also halved, whatever the shares
say: they count frames, and a frame's cost differs between sequences.

Simulated (``python tools/tail_sim.py``: this module's rule fed with simulated rates, held and
queued frames; each worker asks for a task once it holds fewer than 24 frames; 96 tasks of 150
frames; mean of 10 draws), the last worker's end after the balanced end:

* 12 workers at 53 frames/s +- 8 %: 0.34 s against 0.88 s with halving alone; with per-sequence
  frame costs +- 30 %, 0.67 against 1.09;
* 8 workers at 68 frames/s: 0.29 against 0.64; with the costs, 0.39 against 0.91.

In the 4 x H100 rows (J1, bench/RESULTS.md "Ray on four H100s") the workers' last outputs were
1.17 s apart with 12 workers and 0.68 s apart with 8.
"""

from __future__ import annotations

__all__ = ["TailShare", "cut_here", "first_part", "near_end"]

RATE_FRAMES = 16   # a worker's own rate once it has written this many frames after its first report
SHARE_QUEUE = 4    # shares are worked out once fewer than this many tasks a worker are queued (near_end)
CUT_MARGIN = 4     # frames a task may exceed a worker's share by and still go whole


class TailShare:
    """Each worker's rate (frames written over its polls) and its share of a job's work left."""

    def __init__(self) -> None:
        self.since: dict[str, float] = {}   # worker -> when its first frames were reported
        self.frames: dict[str, int] = {}    # worker -> frames reported after those

    def written(self, worker: str, n: int, now: float) -> None:
        """``worker`` reported ``n`` frames written at ``now`` (the first report starts its clock)."""
        if n <= 0:
            return
        if worker not in self.since:
            self.since[worker], self.frames[worker] = now, 0
        else:
            self.frames[worker] += n

    def rate(self, worker: str, now: float) -> float | None:
        n = self.frames.get(worker, 0)
        if n < RATE_FRAMES or now <= self.since[worker]:
            return None
        return n / (now - self.since[worker])

    def share(self, worker: str, held: dict[str, int], queued: int, now: float) -> float | None:
        """The frames ``worker`` can take before the balanced end of the job, given the frames each
        running worker holds (``held``, ``worker`` among them) and the frames ``queued`` (the task
        being handed out included). A worker without a rate yet counts at the others' mean; None
        when no worker has one."""
        rates = {w: self.rate(w, now) for w in held}
        known = [r for r in rates.values() if r is not None]
        if not known or worker not in held:
            return None
        mean = sum(known) / len(known)
        rates = {w: mean if r is None else r for w, r in rates.items()}
        left = queued + sum(held.values())
        return left / sum(rates.values()) * rates[worker] - held[worker]


def cut_here(frames: int, share: float | None, queued_tasks: int, workers: int) -> float | None:
    """Where a task of ``frames`` frames handed out now is cut (frames of its first part; None:
    it goes whole): at the worker's ``share`` (``TailShare.share``) when the task exceeds it by
    more than CUT_MARGIN, and, while the queue (``queued_tasks``, this task not counted) is
    shorter than the job's ``workers``, at its middle if that comes first. The shares count
    frames, but a frame's cost differs between sequences (more or fewer points), so the last
    tasks are halved whatever the shares say (simulated, 12 workers, per-sequence costs +- 30 %:
    the last worker 0.67 s after the balanced end, 1.09 s with halving alone, 0.93 s with the
    shares alone, a variant not kept)."""
    first = max(0.0, share) if share is not None and frames > share + CUT_MARGIN else None
    if queued_tasks < workers:
        first = frames / 2 if first is None else min(first, frames / 2)
    return first


def near_end(queued_tasks: int, workers: int) -> bool:
    """Whether a job with ``queued_tasks`` queued and ``workers`` running is near enough its end
    for shares: fewer than SHARE_QUEUE tasks a worker (before that every worker gets several more
    tasks, and a task goes whole)."""
    return queued_tasks < SHARE_QUEUE * max(1, workers)


def first_part(tail: TailShare, worker: str, frames: int, queued: list[int], held: dict[str, int],
               now: float) -> float | None:
    """Frames of the first part of a task of ``frames`` frames handed to ``worker`` now (None: it
    goes whole), given the frames of each task still ``queued`` and those each running worker
    ``held`` (``worker`` among them). Shares are worked out only when :func:`near_end`."""
    share = tail.share(worker, held, frames + sum(queued), now) if near_end(len(queued), len(held)) else None
    return cut_here(frames, share, len(queued), len(held))
