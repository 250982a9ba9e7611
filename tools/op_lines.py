"""Which lines of the estimator launch the most ATen ops a frame (issue 42: `accurate`'s
GPU-feeding thread is bound by its launches)? Runs ``estimate_sequence`` on one simulated
sequence (bench/_map_data.py's cases, every frame, with the sensor positions as
bench/accurate_map.py passes them) under a ``TorchDispatchMode`` that counts every op that is
not a view, by the innermost ``floxels_ext`` frame that called it; prints ops a frame by
function and by line. On the CPU the counts are those a CUDA run launches (about one kernel
each), without a GPU.

    PYTHONPATH=python python tools/op_lines.py [--preset accurate] [--scene urban] [--seed 60]
        [--beams 32] [--length 11] [--iters 20] [--top 60]
"""

from __future__ import annotations

import argparse
import collections
import sys
import traceback
from pathlib import Path

from torch.utils._python_dispatch import TorchDispatchMode

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from _map_data import sim_case  # noqa: E402
from accurate_map import sensor_kwargs  # noqa: E402

from floxels_ext import FloxelsConfig, estimate_sequence  # noqa: E402

VIEWS = {"view", "unsqueeze", "squeeze", "select", "slice", "expand", "t", "transpose", "alias", "as_strided",
         "detach", "_unsafe_view", "permute", "lift_fresh", "unbind", "split"}


class OpLines(TorchDispatchMode):
    def __init__(self) -> None:
        super().__init__()
        self.count: collections.Counter = collections.Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if func._schema.name.split("::")[-1] not in VIEWS:
            where = "(outside floxels_ext)"
            for fr in reversed(traceback.extract_stack(limit=12)):
                if "floxels_ext" in fr.filename:
                    where = f"{Path(fr.filename).name}:{fr.lineno} {fr.name}"
                    break
            self.count[where] += 1
        return func(*args, **(kwargs or {}))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="accurate")
    ap.add_argument("--scene", default="urban")
    ap.add_argument("--seed", type=int, default=60)
    ap.add_argument("--beams", type=int, default=32)
    ap.add_argument("--length", type=int, default=11)
    ap.add_argument("--iters", type=int, default=20, help="max_iters (the steps after the optimiser see its flow)")
    ap.add_argument("--top", type=int, default=60)
    ap.add_argument("--sim-cache", default=str(ROOT / "bench" / "results" / "accurate_map_cache" / "sim"))
    args = ap.parse_args()
    case = sim_case(args.scene, args.seed, args.beams, args.length, "all", azimuth=2048, cache=Path(args.sim_cache))
    cfg = FloxelsConfig.preset(args.preset).replace(max_iters=args.iters)
    kw = sensor_kwargs(case, cfg, "origins")
    estimate_sequence(case.scans, cfg, device="cpu", frames=case.frames, **kw)  # warm-up
    mode = OpLines()
    with mode:
        estimate_sequence(case.scans, cfg, device="cpu", frames=case.frames, **kw)
    n = len(case.frames)
    print(f"{case.key}, {args.preset}, {n} frames: {sum(mode.count.values()) / n:.1f} ops a frame")
    by_fn: collections.Counter = collections.Counter()
    for k, v in mode.count.items():
        file_line, _, fn = k.partition(" ")
        by_fn[f"{file_line.split(':')[0]} {fn}"] += v
    print("-- by function")
    for k, v in by_fn.most_common(args.top):
        print(f"{v / n:8.1f}  {k}")
    print("-- by line")
    for k, v in mode.count.most_common(args.top):
        print(f"{v / n:8.1f}  {k}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
