"""Progress bars on stderr: tqdm (a core dependency) on a terminal; plain lines otherwise (logs,
CI) or when tqdm is missing.

``Progress(total, label, verbosity)``: verbosity -1 (``floxels -q``) shows no bar; messages
(:meth:`Progress.message`) are printed without garbling the bar in every case. Off a terminal
a line is printed about every 5 % of the work so logs stay short. :class:`DatasetProgress`:
one bar for a whole dataset (frames done, frames/s, ETA) that also counts its sequences done,
skipped (nothing left to do) and failed.
"""

from __future__ import annotations

import sys
import time


def _hms(s: float) -> str:
    s = int(round(s))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"


class Progress:
    def __init__(self, total: int, label: str = "frames", stream=None, verbosity: int = 0) -> None:
        self.total, self.label = max(0, int(total)), label
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = verbosity >= 0
        self.done = 0
        self.t0 = time.perf_counter()
        self._last_pct = -1
        self._bar = None
        if self.enabled and getattr(self.stream, "isatty", lambda: False)():
            try:
                from tqdm import tqdm
            except ImportError:
                tqdm = None
            if tqdm is not None:
                self._bar = tqdm(total=self.total, desc=label, unit="frame", file=self.stream, dynamic_ncols=True,
                                 mininterval=0.5, leave=True)

    def update(self, n: int = 1, note: str = "") -> None:
        self.done += n
        if not self.enabled:
            return
        if self._bar is not None:
            if note:
                self._bar.set_postfix_str(note, refresh=False)
            self._bar.update(n)
            return
        elapsed = time.perf_counter() - self.t0
        rate = elapsed / self.done if self.done else 0.0
        pct = 100 * self.done // self.total if self.total else 100
        if pct // 5 != self._last_pct // 5 or self.done == self.total:
            self._last_pct = pct
            fps = f" ({self.done / elapsed:.1f} frames/s)" if elapsed > 0 and self.done else ""
            print(f"{self.done}/{self.total} {self.label} ({pct}%), {rate:.2f} s/frame{fps}, "
                  f"ETA {_hms(rate * (self.total - self.done))} {note}".rstrip(), file=self.stream, flush=True)

    def message(self, text: str) -> None:
        """Print a line without garbling the bar."""
        if self._bar is not None:
            self._bar.write(text, file=self.stream)
        else:
            print(text, file=self.stream, flush=True)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None


class DatasetProgress(Progress):
    """One bar for a dataset: :meth:`frames` as frames are written or fail, :meth:`sequence`
    as each sequence ends (``"done"``, ``"skipped"``: nothing left to do, ``"failed"``: some of
    its frames, or all of it, failed); the bar's note counts them."""

    def __init__(self, total_frames: int, sequences: int, stream=None, verbosity: int = 0) -> None:
        super().__init__(total_frames, "frames", stream=stream, verbosity=verbosity)
        self.sequences = sequences
        self.counts = {"done": 0, "skipped": 0, "failed": 0}

    def note(self) -> str:
        c = self.counts
        return f"sequences {c['done']}/{self.sequences} done, {c['skipped']} skipped, {c['failed']} failed"

    def frames(self, n: int = 1) -> None:
        self.update(n, note=self.note())

    def sequence(self, outcome: str) -> None:
        self.counts[outcome] += 1
        if self._bar is not None:
            self._bar.set_postfix_str(self.note())
