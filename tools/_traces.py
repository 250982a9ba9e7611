"""What the profiling tools share (``frame_timeline.py``, ``run_gaps.py``): the GPU's busy time
and idle gaps in the events of a torch-profiler Chrome trace."""

from __future__ import annotations

GPU_CATEGORIES = ("kernel", "gpu_memcpy", "gpu_memset")


def gpu_events(events: list) -> list:
    """The events that ran on the GPU (kernels, copies, fills)."""
    return [e for e in events if e.get("cat") in GPU_CATEGORIES and "dur" in e]


def busy_and_gaps(gpu: list) -> tuple[float, float, float, list]:
    """(first start, last end, busy time, idle gaps [(start, length)]) of GPU events (at least
    one), in the trace's microseconds; busy is the union of their intervals over all streams."""
    iv = sorted((e["ts"], e["ts"] + e["dur"]) for e in gpu)
    busy, gaps = 0.0, []
    cur_s, cur_e = iv[0]
    for s, e in iv[1:]:
        if s > cur_e:
            busy += cur_e - cur_s
            gaps.append((cur_e, s - cur_e))
            cur_s, cur_e = s, e
        else:
            cur_e = max(cur_e, e)
    busy += cur_e - cur_s
    return iv[0][0], max(e for _, e in iv), busy, gaps
