"""A Ray job started right after a short one (issue 44's start race), on a local CPU cluster:
the short job ends before all its workers are up; how long does the next job take, and how
many of its workers did it take warm from the pool, start anew, or take late?

    python tools/ray_start_race.py [--rounds 3] [--workers 3]

Prints one line per round (the next job's wall time, first output, its workers' kinds) and
the median. Runs ``floxels run`` in this process, as bench/bench_ray.py does."""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--workers", type=int, default=3)
    ap.add_argument("--frames", type=int, default=8, help="frames of each of the measured job's sequences")
    ap.add_argument("--short-sequences", type=int, default=1,
                    help="sequences of the short job (fewer than --workers: it drops the workers not up yet)")
    args = ap.parse_args()
    import ray

    from floxels_ext import cli
    from floxels_ext.evaluation.seqio import save_sequence
    from floxels_ext.evaluation.sim import simulate_sequence

    tmp = Path(tempfile.mkdtemp(prefix="ray_race_"))
    n = args.workers
    for k in range(args.short_sequences):  # the short job: 2-frame sequences (the first workers up take them)
        save_sequence(tmp / "short" / f"s{k}", simulate_sequence("urban", 2, k, beams=16, azimuth_steps=360))
    for k in range(2 * n):
        save_sequence(tmp / "next" / f"s{k}", simulate_sequence("crossing", args.frames, k, beams=16, azimuth_steps=360))
    flags = ["--ray", "--max-tasks", str(n), "--cpus-per-task", "1", "--device", "cpu", "--max-iters", "3",
             "--scans", "3", "-q"]
    ray.init(address="local", num_cpus=n, include_dashboard=False, log_to_driver=False, _node_ip_address="127.0.0.1")
    walls = []
    try:
        for r in range(args.rounds):
            for name in [a["name"] for a in ray.util.list_named_actors(all_namespaces=True) if a["namespace"] == "floxels"]:
                try:  # an empty pool: the short job starts all its workers
                    ray.get(ray.get_actor(name, namespace="floxels").retire.remote(), timeout=10)
                except (ValueError, ray.exceptions.RayError):
                    pass
            time.sleep(1.0)
            out_s, out_n = tmp / f"o_short{r}", tmp / f"o_next{r}"
            assert cli.main(["run", str(tmp / "short"), "--out", str(out_s), *flags]) == 0
            t0 = time.perf_counter()
            assert cli.main(["run", str(tmp / "next"), "--out", str(out_n), *flags]) == 0
            wall = time.perf_counter() - t0
            info = json.loads((out_n / "ray_job_summary.json").read_text())
            ws = info["workers"]
            first = min((w["timeline"].get("first_output", 1e9) for w in ws), default=None)
            kinds = {"warm": sum(1 for w in ws if w.get("claimed")), "new": sum(1 for w in ws if not w.get("claimed"))}
            walls.append(wall)
            print(f"round {r + 1}: next job {wall:.2f} s, first output {first:.2f} s, workers {kinds}, "
                  f"frames {info['frames_written']}", flush=True)
    finally:
        ray.shutdown()
        shutil.rmtree(tmp, ignore_errors=True)
    print(f"median {statistics.median(walls):.2f} s over {len(walls)} rounds")
    return 0


if __name__ == "__main__":
    sys.exit(main())
