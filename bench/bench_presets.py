"""What the `accurate` preset costs against `paper` (issue 47: at most 2x paper's GPU time per frame).

    python bench/bench_presets.py [--device cpu|cuda] [--beams 32] [--lengths 11] [--scenes urban]
                                  [--seed 60] [--frames ends] [--azimuth 2048] [--max-range 50]
                                  [--iters N] [--repeat 3]
                                  [--variant LABEL=PRESET[,FIELD=VALUE...]] [--no-profile] [--json PATH]

Each row (``paper``, ``accurate`` and every ``--variant``, e.g. ``old=accurate,refine_level=false``)
estimates the scored frames of simulated sequences (bench/_map_data.py's cases: beams x lengths x
scenes, one seed) as an API user does, and as bench/accurate_map.py times them: one
``estimate_sequence`` call over the whole sequence for the scored frames (``--frames``: ``ends``,
the first, middle and last frame; ``all``; or a comma list), with each scan's sensor position and,
where the row's ``visibility`` reads it, its removed ground. Per row and case:

* wall seconds per frame: the median of ``--repeat`` timed calls after one warm-up call
  (synchronised on CUDA);
* on CUDA, from one more call under ``torch.profiler`` (CUDA activity): the GPU's kernel time per
  frame (every kernel's duration summed, memory copies and fills apart) and its busy time (the
  union of kernel intervals over all streams); ``--no-profile`` leaves it out;
* on CUDA, the host synchronisations per frame of one more call (``torch.cuda.set_sync_debug_mode``
  warnings: reads of device values, blocking copies);
* the ratios of each to ``paper``'s on the same case.

The table ends with the rows' totals over all cases (time per frame over every scored frame).
The CPU defaults are a smoke test (32 beams x 512 azimuth steps need ``--azimuth 512``; ``--iters``
caps ``max_iters`` of every row: a smoke run only, the accurate/paper ratio changes with it).
The JSON (``--json``, default bench/results/bench_presets.json) holds every number and the command.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
import warnings
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _map_data import SCENES, sim_case  # noqa: E402
from _timing import write_results  # noqa: E402
from accurate_map import parse_variant, sensor_kwargs  # noqa: E402

from floxels_ext import FloxelsConfig, estimate_sequence  # noqa: E402

SIM_CACHE = HERE / "results" / "accurate_map_cache" / "sim"  # shared with accurate_map.py


def sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def gpu_times(fn) -> dict:
    """Kernel time and busy time (ms) on the GPU of one call of ``fn`` (torch.profiler)."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        fn()
    kernels, copies = [], 0.0
    for e in prof.events():
        if e.device_type != torch.autograd.DeviceType.CUDA:
            continue
        a, b = e.time_range.start, e.time_range.end
        if e.name.startswith(("Memcpy", "Memset")) or "memcpy" in e.name.lower() or "memset" in e.name.lower():
            copies += b - a
        else:
            kernels.append((a, b))
    busy, end = 0.0, float("-inf")
    for a, b in sorted(kernels):  # union of the kernels' intervals
        if b > end:
            busy += b - max(a, end)
            end = b
    return {"kernel_ms": 1e-3 * sum(b - a for a, b in kernels), "busy_ms": 1e-3 * busy,
            "copy_ms": 1e-3 * copies, "kernels": len(kernels)}


def count_syncs(fn) -> int:
    """Host synchronisations of one call of ``fn`` that CUDA's sync debug mode reports."""
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")
        try:
            fn()
        finally:
            torch.cuda.set_sync_debug_mode(0)
    return sum("synchroniz" in str(w.message).lower() for w in got)


def measure(case, cfg: FloxelsConfig, args) -> dict:
    kw = sensor_kwargs(case, cfg, "origins")
    frames = case.frames
    n = len(frames)

    def call():
        estimate_sequence(case.scans, cfg, device=args.device, frames=frames, **kw)
        sync(args.device)

    call()  # warm-up: every path the row takes initialised
    walls = []
    for _ in range(args.repeat):
        sync(args.device)
        t0 = time.perf_counter()
        call()
        walls.append(time.perf_counter() - t0)
    row = {"wall_s_per_frame": statistics.median(walls) / n, "wall_runs_s": walls, "frames": n}
    if args.device.startswith("cuda"):
        if not args.no_profile:
            g = gpu_times(call)
            row.update({"gpu_kernel_ms_per_frame": g["kernel_ms"] / n, "gpu_busy_ms_per_frame": g["busy_ms"] / n,
                        "gpu_copy_ms_per_frame": g["copy_ms"] / n, "kernels_per_frame": g["kernels"] / n})
        row["syncs_per_frame"] = count_syncs(call) / n
    return row


RATIOS = {"wall_s_per_frame": "wall_x_paper", "gpu_kernel_ms_per_frame": "gpu_kernel_x_paper",
          "gpu_busy_ms_per_frame": "gpu_busy_x_paper"}


def add_ratios(rows: dict) -> None:
    base = rows["paper"]
    for r in rows.values():
        for k, name in RATIOS.items():
            if k in r and base.get(k):
                r[name] = r[k] / base[k]


def totals(cases: list[dict], labels: list[str]) -> dict:
    """Per row, every case's per-frame figures weighted by its scored frames."""
    out = {}
    for lab in labels:
        rs = [c["rows"][lab] for c in cases]
        frames = sum(r["frames"] for r in rs)
        t = {"frames": frames}
        for k in ("wall_s_per_frame", "gpu_kernel_ms_per_frame", "gpu_busy_ms_per_frame", "syncs_per_frame",
                  "kernels_per_frame"):
            if all(k in r for r in rs):
                t[k] = sum(r[k] * r["frames"] for r in rs) / frames
        out[lab] = t
    add_ratios(out)
    return out


def print_table(title: str, rows: dict, cuda: bool) -> None:
    cols = [("wall ms/frame", "wall_s_per_frame", 1e3), ("x paper", "wall_x_paper", 1)]
    if cuda:
        cols += [("GPU kernel ms/frame", "gpu_kernel_ms_per_frame", 1), ("x paper", "gpu_kernel_x_paper", 1),
                 ("GPU busy ms/frame", "gpu_busy_ms_per_frame", 1), ("x paper", "gpu_busy_x_paper", 1),
                 ("kernels/frame", "kernels_per_frame", 1), ("syncs/frame", "syncs_per_frame", 1)]
    print(f"\n{title}\n")
    print("| row | " + " | ".join(c[0] for c in cols) + " |")
    print("| --- |" + " --- |" * len(cols))
    for lab, r in rows.items():
        cells = []
        for _, k, scale in cols:
            v = r.get(k)
            cells.append("n/a" if v is None else f"{v * scale:.2f}" if "x_paper" in k else f"{v * scale:.1f}")
        print(f"| {lab} | " + " | ".join(cells) + " |")


def parse_args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--beams", nargs="+", type=int, default=[32])
    ap.add_argument("--lengths", nargs="+", type=int, default=[11])
    ap.add_argument("--scenes", nargs="+", default=["urban"], choices=SCENES)
    ap.add_argument("--seed", type=int, default=60, help="simulator seed (60-62: held out from the preset's tuning)")
    ap.add_argument("--frames", default="ends", help="scored frames of each sequence: ends, all, or 0,5,-1")
    ap.add_argument("--azimuth", type=int, default=2048, help="simulated lidar azimuth steps")
    ap.add_argument("--max-range", type=float, default=50.0, help="the protocol's crop of the simulated scans (m)")
    ap.add_argument("--iters", type=int, default=0, help="cap max_iters of every row (smoke runs; 0: the presets')")
    ap.add_argument("--repeat", type=int, default=3, help="timed calls per row and case (median)")
    ap.add_argument("--variant", action="append", default=[], metavar="LABEL=PRESET[,FIELD=VALUE...]",
                    help="rows besides paper and accurate")
    ap.add_argument("--no-profile", action="store_true", help="CUDA: no profiled call (no GPU kernel time)")
    ap.add_argument("--sim-cache", default=str(SIM_CACHE), help="directory of the simulated sequences ('' : none)")
    ap.add_argument("--json", default=None, help="default: bench/results/bench_presets.json")
    args = ap.parse_args(argv)
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        ap.error("--device cuda requested but no CUDA device is available")
    if args.repeat < 1 or args.iters < 0:
        ap.error("--repeat must be >= 1 and --iters >= 0")
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    variants = [("paper", FloxelsConfig()), ("accurate", FloxelsConfig.preset("accurate"))]
    try:
        variants += [parse_variant(v) for v in args.variant]
    except ValueError as e:
        raise SystemExit(f"bench_presets: error: {e}")
    if args.iters:
        variants = [(lab, cfg.replace(max_iters=args.iters)) for lab, cfg in variants]
    labels = [lab for lab, _ in variants]
    cuda = args.device.startswith("cuda")
    cache = Path(args.sim_cache) if args.sim_cache else None
    cases, t_all = [], time.perf_counter()
    for scene in args.scenes:
        for beams in args.beams:
            for length in args.lengths:
                case = sim_case(scene, args.seed, beams, length, args.frames, max_range=args.max_range,
                                azimuth=args.azimuth, cache=cache)
                rows = {lab: measure(case, cfg, args) for lab, cfg in variants}
                add_ratios(rows)
                pts = sum(case.scans[f].shape[0] for f in case.frames) / len(case.frames)
                cases.append({"case": case.key, "frames": case.frames, "points_per_frame": pts, "rows": rows})
                print_table(f"{case.key}: frames {case.frames}, {pts:.0f} points a frame", rows, cuda)
    total = totals(cases, labels)
    print_table(f"all {len(cases)} cases ({args.device})", total, cuda)
    dev = torch.cuda.get_device_name() if cuda else platform.processor() or "cpu"
    write_results({"command": "python bench/bench_presets.py " + " ".join(sys.argv[1:] if argv is None else argv),
                   "device": args.device, "device_name": dev, "host": platform.node(),
                   "threads": torch.get_num_threads(), "cpu_count": os.cpu_count(),
                   "variants": {lab: {k: v for k, v in vars(cfg).items()} for lab, cfg in variants},
                   "cases": cases, "totals": total, "total_seconds": time.perf_counter() - t_all},
                  args.json, "bench_presets.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
