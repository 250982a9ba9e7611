"""When the engines of ``floxels run --engines N`` joined a run: each engine's first frame, the
moment the last one wrote its first, and the rate from then on (``run_summary.json``'s
``engines_start``).

Why: engines 1..N-1 start beside the run (a process, the fork server's imports, a CUDA context,
a warm-up) and join seconds after engine 0. A 768-frame `accurate` run on one H200 ran its first
quarter at one engine's rate and the rest at about twice its end-to-end figure
(bench/RESULTS.md, "Where a 768-frame `floxels run` loses half its rate"): the summary says how
much of a run was that start, and bench/bench_run.py times the steady part from it. A run of few
frames can end before the others are ready: ``all_joined_s`` is then None.
"""

from __future__ import annotations

import time

__all__ = ["JoinClock"]


class JoinClock:
    """Frames as the run hears of them (call :meth:`frame` under the run's lock)."""

    def __init__(self, engines: int) -> None:
        self.n = engines
        self.t0 = time.time()
        self.first: dict[int, float] = {}   # engine -> its first frame (s from the run's start)
        self.written = 0                    # frames written so far (failed ones not counted)
        self.joined: tuple[float, int] | None = None  # (s, frames written by then) once all N wrote one
        self.last: float | None = None      # the last frame written (s)

    def frame(self, engine: int, ok: bool) -> None:
        now = time.time() - self.t0
        if ok:
            self.written += 1
            self.last = now
        if engine not in self.first:  # a failed frame is the engine at work too
            self.first[engine] = now
            if len(self.first) == self.n:
                self.joined = (now, self.written)

    def summary(self) -> dict:
        """``run_started_at`` (time.time()); seconds from it: each engine's ``first_frame_s``,
        ``all_joined_s`` and ``last_frame_s``; ``frames_per_s_after_join``: frames written after
        the last engine's first, over the time from it to the last frame (None where not all
        joined, or nothing came after)."""
        out = {"run_started_at": round(self.t0, 3),
               "first_frame_s": {str(e): round(t, 3) for e, t in sorted(self.first.items())},
               "all_joined_s": None, "last_frame_s": None if self.last is None else round(self.last, 3),
               "frames_per_s_after_join": None}
        if self.joined is not None:
            t, k = self.joined
            out["all_joined_s"] = round(t, 3)
            if self.last is not None and self.last > t and self.written > k:
                out["frames_per_s_after_join"] = round((self.written - k) / (self.last - t), 2)
        return out
