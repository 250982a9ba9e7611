"""Timing and result files shared by the bench scripts (run as `python bench/bench_X.py`, so bench/ is on sys.path)."""

from __future__ import annotations

import json
import os
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


def write_results(out: dict, path: str | None, default_name: str) -> str:
    """Writes ``out`` as JSON to ``path`` (default: ``bench/results/<default_name>``) and
    says where."""
    path = path or os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", default_name)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w") as fh:
        json.dump(out, fh, indent=1, default=float)
    print(f"wrote {path}")
    return path

