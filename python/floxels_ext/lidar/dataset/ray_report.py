"""What a Ray job of ``floxels run --ray`` tells its user at its end: each worker's start
timeline (``-v``), a warning for a worker that sees more GPUs than Ray gave it, and
``OUT/ray_job_summary.json`` (counts, wall time, every worker's timeline)."""

from __future__ import annotations

import json
import math
import os
import sys
from pathlib import Path

__all__ = ["format_timeline", "report_workers", "write_job_summary"]

# the stamps of a worker's start and run (ray_worker.FloxelsWorker), in the order they happen
_STEPS = {"requested": "requested", "process": "process", "imported": "imported",
          "preloaded": "preloaded (torch, ops)", "init": "init",
          "torch": "torch + ops", "init_done": "init done", "warm_imports": "imports", "cuda_context": "CUDA context",
          "warm_done": "warm-up done", "run": "run", "pipeline": "pipeline", "first_task": "first task",
          "first_output": "first output", "last_output": "last output", "task_ended": "tasks ended",
          "end": "end"}


def format_timeline(tl: dict) -> str:
    """A worker's start as 'name +s' steps in time order (s from the job's start; negative:
    before it, a warm worker or a preloaded process)."""
    order = list(_STEPS)
    steps = sorted((v, order.index(k), k) for k, v in tl.items() if k in _STEPS and isinstance(v, (int, float)))
    return ", ".join(f"{_STEPS[k]} {v:+.2f}" for v, _, k in steps)


def report_workers(results: list[dict], verbosity: int) -> None:
    """The warning for GPUs a worker should not see, and (``-v``) each worker's timeline."""
    for r in results:  # every worker would use the first visible GPU: GPUs shared, others idle
        if r.get("gpus") and (r.get("cuda_devices") or 0) > len(r["gpus"]):
            print(f"floxels: warning: {r['name']} sees {r['cuda_devices']} GPUs though Ray gave it "
                  f"{len(r['gpus'])}: CUDA was initialised in its process before Ray placed it (a module "
                  "preloaded into Ray's workers must not touch CUDA)", file=sys.stderr)
    if verbosity > 0:
        for r in sorted(results, key=lambda r: r["timeline"].get("first_output", math.inf)):
            kind = "warm, from the pool" if r["claimed"] else "started for this job"
            print(f"  {r['name']} ({r['host']} pid {r['pid']}, {kind}; GPU {','.join(r['gpus']) or '-'}; "
                  f"{r['written']} frames): {format_timeline(r['timeline'])}"
                  + (f"; warm-up failed: {r['warm_error']}" if r.get("warm_error") else ""), file=sys.stderr)


def write_job_summary(path: Path, info: dict) -> None:
    """``info`` as JSON at ``path``, replaced whole (a warning, not an error, when it cannot)."""
    try:
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        tmp.write_text(json.dumps(info, indent=1, default=str) + "\n")
        os.replace(tmp, path)
    except OSError as e:
        print(f"floxels: warning: cannot write {path}: {e}", file=sys.stderr)
