"""Timing shared by the bench scripts (run as `python bench/bench_X.py`, so bench/ is on sys.path)."""

from __future__ import annotations

import statistics
import time

import torch


def timeit(fn, device: str, repeats: int, warmup: int = 2) -> float:
    """Median milliseconds of ``fn()`` after ``warmup`` calls. On CUDA: events around each
    call (host dispatch included when the GPU waits for it)."""
    for _ in range(warmup):
        fn()
    times = []
    if device == "cuda":
        torch.cuda.synchronize()
    for _ in range(repeats):
        if device == "cuda":
            a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            a.record()
            fn()
            b.record()
            b.synchronize()
            times.append(a.elapsed_time(b))
        else:
            t0 = time.perf_counter()
            fn()
            times.append(1e3 * (time.perf_counter() - t0))
    return statistics.median(times)
