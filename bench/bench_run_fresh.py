"""``floxels run`` as a user starts it: a fresh process per run (its imports, CUDA context, fork
server and engines all start inside the timed wall), on bench_run.py's simulated KITTI and AV2
layout files. bench_run.py times runs in one warmed-up process instead (engine 0 warm, the fork
server kept between runs), which hides the start a user pays once per command.

    python bench/bench_run_fresh.py --frames 768 --data /tmp/ab_data [--repeat 2] [--run-args "--preset paper"]

Prints, per run: the process's wall (start-up included), frames/s over it, the run's own
frames/s (``run_summary.json``: from its first task to its end), and writes JSON
(``--json``; ``tools/ab_bench.py --benches fresh`` reads ``runs.<layout>.frames_per_s``: the
median over --repeat of the frames/s over the process's wall).
"""

from __future__ import annotations

import argparse
import json
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))


def main() -> None:
    from bench_run import built

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=64)
    ap.add_argument("--beams", type=int, default=128)
    ap.add_argument("--azimuth", type=int, default=1800)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--data", type=Path, help="bench_run.py's --data: the simulated files, reused when they match")
    ap.add_argument("--device", default=None, help="floxels run's --device (default: its own)")
    ap.add_argument("--run-args", default="", help="extra floxels run arguments (quoted)")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--json", default="bench/results/bench_run_fresh.json")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench_run_fresh_"))
    kitti, av2, npts, how = built(args, tmp)
    print(f"sequence: {args.frames} frames, {args.beams} beams, {npts} raw points a frame ({how})", flush=True)
    extra = [*(["--device", args.device] if args.device else []), *shlex.split(args.run_args)]
    layouts = {"kitti": [str(kitti / "velodyne"), "--poses", str(kitti / "poses.txt")], "av2": [str(av2)]}
    runs: dict[str, list] = {k: [] for k in layouts}
    for rep in range(args.repeat):
        for name, argv in layouts.items():
            out = tmp / f"out_{name}_{rep}"
            t0 = time.perf_counter()
            rc = subprocess.run([sys.executable, "-m", "floxels_ext", "run", *argv, "--out", str(out), "-q",
                                 *extra]).returncode
            wall = time.perf_counter() - t0
            if rc != 0:
                sys.exit(f"bench_run_fresh.py: floxels run failed (exit {rc}) on {name}")
            s = json.loads((out / "run_summary.json").read_text())
            row = {"process_wall_s": round(wall, 3), "frames_per_s": s["written"] / wall,
                   "run_frames_per_s": s.get("frames_per_s"), "engines": s.get("engines", 1), "mps": s.get("mps")}
            runs[name].append(row)
            print(f"{name} (run {rep + 1}): process {wall:.2f} s, {row['frames_per_s']:.1f} frames/s over it; "
                  f"the run's own {row['run_frames_per_s']} frames/s; {row['engines']} engine(s), mps {row['mps']}",
                  flush=True)
    result = {"frames": args.frames, "run_args": args.run_args, "repeat": args.repeat,
              "runs": {k: {"frames_per_s": statistics.median(r["frames_per_s"] for r in v),
                           "process_wall_s": statistics.median(r["process_wall_s"] for r in v), "repeats": v}
                       for k, v in runs.items()}}
    print(f"\n{'layout':<8}{'frames/s (process wall)':>26}{'process wall s':>16}   (medians of {args.repeat})")
    for k, v in result["runs"].items():
        print(f"{k:<8}{v['frames_per_s']:>26.1f}{v['process_wall_s']:>16.2f}")
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
