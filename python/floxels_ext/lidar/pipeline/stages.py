"""Where ``floxels run``'s time goes: :class:`Stages`, seconds per stage of the run, added up by
the threads that do the work (readers, transform threads, the optimiser's thread, writers) and
written to ``run_summary.json`` (``stages_s``)."""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

__all__ = ["Stages"]


@dataclass
class Stages:
    """Seconds per stage. read/preprocess/write: summed over worker threads (CPU time spent);
    wait_input: the optimiser waited for frames; estimate: inside the method; wait_writer: the
    optimiser waited for the writer (queue full); deliver: the optimiser handed results over (its
    callback per frame, wait_writer included); wall: the whole pipeline. ``wait_input_in_estimate``:
    the part of wait_input spent inside the method (it asks for the scans lazily), so
    ``estimate - wait_input_in_estimate`` is the time the method actually computed."""

    read: float = 0.0
    preprocess: float = 0.0
    transform: float = 0.0
    estimate: float = 0.0
    write: float = 0.0
    wait_input: float = 0.0
    wait_input_in_estimate: float = 0.0
    wait_writer: float = 0.0
    deliver: float = 0.0
    wall: float = 0.0
    in_estimate: bool = False  # set by the thread calling the method
    optimiser_thread: int | None = None  # its threading.get_ident(): only its waits count
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def waited(self, dt: float) -> None:
        """The calling thread waited ``dt`` s for a frame: counted when it is the optimiser's
        thread (the transform threads wait for loads too, but the device does not)."""
        if self.optimiser_thread is not None and threading.get_ident() != self.optimiser_thread:
            return
        self.add("wait_input", dt)
        if self.in_estimate:
            self.add("wait_input_in_estimate", dt)

    def add(self, name: str, dt: float) -> None:
        with self._lock:
            setattr(self, name, getattr(self, name) + dt)

    def as_dict(self) -> dict:
        d = {k: round(getattr(self, k), 6) for k in
             ("read", "preprocess", "transform", "estimate", "write", "wait_input", "wait_input_in_estimate",
              "wait_writer", "deliver", "wall")}
        # the method waits for nothing but its own work: the rest of the wall time is host-bound
        d["compute"] = round(max(0.0, self.estimate - self.wait_input_in_estimate - self.wait_writer), 6)
        d["outside_estimate"] = round(max(0.0, self.wall - self.estimate), 6)
        d["host_bound"] = round(max(0.0, self.wall - d["compute"]), 6)
        return d
