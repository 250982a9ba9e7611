"""A minimal progress printer on stderr (no tqdm dependency).

On a terminal it redraws one line (bar, count, s/frame, ETA); otherwise (logs, CI) it prints a
plain line about every 5 % of the work so logs stay short.
"""

from __future__ import annotations

import sys
import time


def _hms(s: float) -> str:
    s = int(round(s))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"


class Progress:
    def __init__(self, total: int, label: str = "frames", stream=None, width: int = 28) -> None:
        self.total, self.label, self.width = max(0, int(total)), label, width
        self.stream = stream if stream is not None else sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.done = 0
        self.t0 = time.perf_counter()
        self._last_pct = -1

    def update(self, n: int = 1, note: str = "") -> None:
        self.done += n
        elapsed = time.perf_counter() - self.t0
        rate = elapsed / self.done if self.done else 0.0
        eta = rate * (self.total - self.done)
        pct = 100 * self.done // self.total if self.total else 100
        if self.tty:
            fill = self.width * self.done // self.total if self.total else self.width
            line = (f"\r[{'#' * fill}{'.' * (self.width - fill)}] {self.done}/{self.total} {self.label} "
                    f"{rate:.2f} s/frame ETA {_hms(eta)} {note}")
            self.stream.write(line[:160].ljust(100))
            self.stream.flush()
        elif pct // 5 != self._last_pct // 5 or self.done == self.total:
            self._last_pct = pct
            print(f"{self.done}/{self.total} {self.label} ({pct}%), {rate:.2f} s/frame, ETA {_hms(eta)} {note}".rstrip(),
                  file=self.stream, flush=True)

    def message(self, text: str) -> None:
        """Print a line without garbling the bar."""
        if self.tty:
            self.stream.write("\r" + " " * 100 + "\r")
        print(text, file=self.stream, flush=True)

    def close(self) -> None:
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()
