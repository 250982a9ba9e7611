"""Which of ``floxels run``'s concurrent work slows its optimiser (issue 16)? The method computes
~1 ms a frame slower inside the run than ``estimate_sequence`` on scans already in memory (the
ceiling of bench/bench_run.py). This times the same KITTI-style run with the concurrency taken
away one part at a time (measurement-only patches, nothing shipped changes):

* ``default``: as users run it;
* ``preread``: every frame read, preprocessed and moved into the chunk's frame before the method
  starts (readers idle while it computes);
* ``preread+deferred``: also no writes until the method is done (writers idle while it computes);

and reports the method's compute time per frame (``stages.compute``) of each next to the ceiling,
interleaved ``--repeat`` times (medians).

    python tools/run_isolation.py [--frames 64] [--repeat 3]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from bench_run import build, ceiling, run_cli  # noqa: E402

import floxels_ext.lidar.dataset.layout as layout  # noqa: E402
import floxels_ext.lidar.dataset.stream as engine  # noqa: E402
from floxels_ext.lidar.dataset.layout import StreamScans  # noqa: E402
from floxels_ext.lidar.pipeline.frame_writer import WriterPool  # noqa: E402


class PrereadScans(StreamScans):
    """Reads and transforms every scan of the run before the method sees one."""

    def __init__(self, lay, stages) -> None:
        super().__init__(lay, stages)
        while lay.extend(block=True):
            pass
        for g in range(lay.end):
            self._submit(g)
        self._next = lay.end
        for fut in list(self._futs.values()):
            fut.result()


def deferred_writes(on: bool) -> None:
    """WriterPool.put keeps results until close (then writes them as usual)."""
    if not hasattr(WriterPool, "_orig_put"):
        WriterPool._orig_put, WriterPool._orig_close = WriterPool.put, WriterPool.close
    if not on:
        WriterPool.put, WriterPool.close = WriterPool._orig_put, WriterPool._orig_close
        return

    def put(self, *item, **kw):
        self.__dict__.setdefault("_held", []).append((item, kw))

    def close(self):
        for item, kw in self.__dict__.pop("_held", []):
            WriterPool._orig_put(self, *item, **kw)
        WriterPool._orig_close(self)

    WriterPool.put, WriterPool.close = put, close


def configure(mode: str) -> None:
    pre = mode.startswith("preread")
    engine.StreamScans = PrereadScans if pre else StreamScans
    layout.READ_AHEAD = 1 << 30 if pre else 64
    deferred_writes(mode.endswith("deferred"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=64)
    ap.add_argument("--beams", type=int, default=128)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--max-iters", type=int)
    a = ap.parse_args()
    modes = ["default", "preread", "preread+deferred"]
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        kitti, _, npts = build(tmp, a.frames, a.beams, 1800, 0)
        common = ["--device", a.device, "-q"] + (["--max-iters", str(a.max_iters)] if a.max_iters else [])
        src = [str(kitti / "velodyne"), "--poses", str(kitti / "poses.txt")]
        run_cli(["run", *src, "--out", str(tmp / "warm"), "--frames", "0:6", *common])
        got: dict[str, list] = {m: [] for m in modes}
        for rep in range(a.repeat):
            for m in modes:
                configure(m)
                t0 = time.perf_counter()
                wall, summ = run_cli(["run", *src, "--out", str(tmp / f"{m}_{rep}"), *common])
                st = summ["stages_s"]
                got[m].append((summ["written"] / wall, 1e3 * st["compute"] / a.frames,
                               1e3 * (wall - st["compute"]) / a.frames, time.perf_counter() - t0))
        configure("default")
        ceil = ceiling(kitti, 5, a.device, {} if a.max_iters is None else {"max_iters": a.max_iters}, repeat=a.repeat)
    c_ms = 1e3 * ceil["estimate_s"] / a.frames
    print(f"{a.frames} frames of {npts} raw points, {a.device}; medians of {a.repeat} (ms a frame)")
    print(f"{'mode':>18} | {'frames/s':>8} | {'compute':>7} | {'not computing':>13} | compute vs ceiling")
    for m in modes:
        fps, comp, rest = (statistics.median(v[k] for v in got[m]) for k in range(3))
        print(f"{m:>18} | {fps:8.1f} | {comp:7.2f} | {rest:13.2f} | {comp / c_ms:.2f}x")
    print(f"{'ceiling':>18} | {ceil['frames_per_s']:8.1f} | {c_ms:7.2f} |")


if __name__ == "__main__":
    main()
