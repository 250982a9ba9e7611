"""The number of torch CPU threads the ``floxels`` commands use for CPU work (``demo``, ``run
--device cpu``), chosen from the cores and the work already running on them.

torch's default is one thread per core. Its OpenMP parallel regions end in a barrier, so
when other processes keep the cores busy every region waits for its slowest, descheduled
thread. Measured on the 2-core development machine (``python bench/bench_threads.py``,
bench/RESULTS.md, "CPU threads"): with the machine loaded by other jobs (load average 12-14)
the demo frame took 55-58 s with 2 threads and 23 s with 1; on the idle machine 2 threads are
the faster (docs/benchmarks.md, "CPU threads"). Results do not depend on the thread count.

The rule: as many threads as cores the 1-minute load average leaves free (rounded), at least
1; ``OMP_NUM_THREADS`` set by the user wins, and the library API never changes torch's
setting (only the commands do).
"""

from __future__ import annotations

import os

__all__ = ["usable_cores", "choose_cpu_threads", "apply_cpu_threads"]


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity where the OS has one)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def choose_cpu_threads(cores: int | None = None, load: float | None = None) -> int:
    """Threads for CPU work: the cores that the load average (other runnable work) leaves
    free, rounded, at least 1."""
    if cores is None:
        cores = usable_cores()
    if load is None:
        try:
            load = os.getloadavg()[0]
        except (OSError, AttributeError):
            load = 0.0
    return max(1, min(cores, int(cores - load + 0.5)))


def apply_cpu_threads(report=None) -> int | None:
    """Set torch's CPU threads by :func:`choose_cpu_threads` unless ``OMP_NUM_THREADS`` is
    set; returns the number set (None: left alone). ``report(msg)`` says what was chosen."""
    if os.environ.get("OMP_NUM_THREADS"):
        return None
    import torch

    n = choose_cpu_threads()
    if n != torch.get_num_threads():
        torch.set_num_threads(n)
    if report is not None:
        try:
            load = os.getloadavg()[0]
        except (OSError, AttributeError):
            load = float("nan")
        report(f"CPU threads: {n} (load average {load:.1f}; OMP_NUM_THREADS=N overrides)")
    return n
