"""``floxels simulate``: write a synthetic lidar sequence with exact ground-truth flow."""

from __future__ import annotations

import time
from pathlib import Path

from floxels_ext.cli import CLIError

# Cost model of the simulator, measured with bench-free runs on the 2-core CPU machine (urban
# scene, 64-512 beams x 2048 azimuth steps): one frame's ray casting peaks at ~260 bytes per
# ray (float64 ray directions, lengths, hit ids and the slab test's temporaries), each kept
# point costs ~40 bytes until the sequence is written (points, flow, labels of every frame),
# plus ~250 MB of interpreter, numpy and torch; ~3.5 us per ray and frame on one core.
BYTES_PER_RAY = 260
BYTES_PER_POINT = 40
BASE_BYTES = 250e6
SECONDS_PER_RAY = 3.5e-6


def simulation_cost(beams: int, azimuth_steps: int, frames: int) -> tuple[float, float]:
    """(estimated peak memory in bytes, estimated seconds) of ``floxels simulate``."""
    rays = beams * azimuth_steps
    return BASE_BYTES + BYTES_PER_RAY * rays + BYTES_PER_POINT * rays * frames, SECONDS_PER_RAY * rays * frames


def default_memory_limit() -> float:
    """Half the memory available now (Linux: MemAvailable), else 8 GB."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return 0.5 * int(line.split()[1]) * 1024
    except OSError:
        pass
    return 8e9


# The names of sim.scenes.SCENES, spelt out: importing the simulator (numpy and all) for the
# parser would slow down every `floxels --help`; tests/test_cli_startup.py checks they agree.
SCENE_NAMES = ("crossing", "highway", "parking", "urban")


def add_parser(sub) -> None:
    p = sub.add_parser("simulate", help="write a synthetic lidar sequence with ground-truth flow",
                       description="Simulate a spinning lidar in a synthetic scene and write one .npz per frame "
                                   "(points, pose, flow, classes, instance, ground, dynamic).")
    p.add_argument("out_dir", metavar="OUT_DIR", help="output sequence directory")
    p.add_argument("--scene", choices=SCENE_NAMES, default="urban")
    from floxels_ext.cli_types import finite_float, nonnegative_float, nonnegative_int, positive_float, positive_int

    p.add_argument("--seed", type=nonnegative_int, default=0)
    p.add_argument("--frames", type=int, default=13, help="number of frames (default 13)")
    p.add_argument("--small", action="store_true", help="32 beams x 512 azimuth steps (fast)")
    p.add_argument("--beams", type=positive_int, help="number of lidar beams (default 64)")
    p.add_argument("--azimuth-steps", type=positive_int, help="firings per revolution (default 2048)")
    p.add_argument("--max-range", type=positive_float, help="metres (default 70)")
    p.add_argument("--range-noise", type=nonnegative_float, help="range noise std-dev in metres (default 0.02; 0.015 with --boxes)")
    p.add_argument("--dropout", type=finite_float, help="probability of losing a return (default 0.05)")
    p.add_argument("--boxes", "--no-vehicle-detail", dest="vehicle_detail", action="store_false",
                   help="vehicles as plain boxes, as the simulator made them before vehicle detail "
                        "(reproduces earlier output)")
    p.add_argument("--force", action="store_true", help="replace frames already in OUT_DIR")
    p.add_argument("--max-memory", type=positive_float, metavar="GB",
                   help="refuse settings whose estimated peak memory exceeds this (default: half the memory "
                        "available now); the estimate is printed with -v")
    p.set_defaults(func=_run_simulate)


def _run_simulate(args) -> int:
    from floxels_ext.evaluation import seqio
    from floxels_ext.evaluation.sim import simulate_sequence

    if args.frames < 1:
        raise CLIError("--frames must be >= 1")
    if not args.out_dir.strip():  # Path('') is the current directory: never meant
        raise CLIError("OUT_DIR is empty; give the directory to write the sequence to")
    out = Path(args.out_dir)
    if out.exists() and not out.is_dir():
        raise CLIError(f"{out} exists and is not a directory")
    old = sorted(out.glob("[0-9][0-9][0-9][0-9][0-9][0-9].npz")) if out.is_dir() else []
    if old and not args.force:
        raise CLIError(f"{out} already holds {len(old)} frame file(s); use --force to replace them")
    opts = {k: v for k, v in (("beams", args.beams), ("azimuth_steps", args.azimuth_steps),
                              ("max_range", args.max_range), ("range_noise", args.range_noise),
                              ("dropout", args.dropout)) if v is not None}
    from floxels_ext.evaluation.sim.lidar import SMALL_LIDAR, LidarConfig

    base = SMALL_LIDAR if args.small else {}
    beams = opts.get("beams", base.get("beams", LidarConfig.beams))
    steps = opts.get("azimuth_steps", base.get("azimuth_steps", LidarConfig.azimuth_steps))
    mem, secs = simulation_cost(beams, steps, args.frames)
    limit = args.max_memory * 1e9 if args.max_memory is not None else default_memory_limit()
    if mem > limit:  # before any work: --beams 100000 grew to 23 GB and was killed after 126 s
        raise CLIError(f"{beams} beams x {steps} azimuth steps = {beams * steps:,} rays a frame, {args.frames} "
                       f"frame(s): an estimated {mem / 1e9:.1f} GB of memory (and ~{secs:.0f} s on one core), above "
                       f"the limit of {limit / 1e9:.1f} GB ({'--max-memory' if args.max_memory is not None else 'half the available memory; --max-memory GB changes it'}); "
                       f"use fewer --beams, --azimuth-steps or --frames")
    if getattr(args, "verbosity", 0) > 0 or secs > 60:
        print(f"simulating {args.frames} frame(s) of {beams} x {steps} rays: estimated {mem / 1e9:.1f} GB peak memory, "
              f"~{secs:.0f} s on one core", flush=True)
    from floxels_ext.output_paths import check_writable_dir

    check_writable_dir(out, "OUT_DIR")  # a read-only place before the work, not a traceback after it
    t0 = time.perf_counter()
    try:
        seq = simulate_sequence(args.scene, args.frames, args.seed, small=args.small,
                                vehicle_detail=args.vehicle_detail, **opts)
    except ValueError as e:  # invalid lidar settings
        raise CLIError(str(e)) from None
    for p in old:
        p.unlink()
    seqio.save_sequence(out, seq)
    n = [len(f) for f in seq.frames]
    dyn = sum(int(f.dynamic.sum()) for f in seq.frames)
    print(f"wrote {len(n)} frames of scene '{args.scene}' (seed {args.seed}) to {out}: "
          f"{min(n)}-{max(n)} points/frame, {dyn} dynamic points, {time.perf_counter() - t0:.1f} s")
    return 0
