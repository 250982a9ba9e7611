"""``floxels demo``: Floxels on a built-in simulated scene, with metrics, timing and a picture."""

from __future__ import annotations

import argparse
import time
from pathlib import Path


def add_parser(sub) -> None:
    p = sub.add_parser("demo", help="run Floxels on a built-in simulated scene and report accuracy",
                       description="Simulates a short lidar sequence (exact ground truth), estimates the "
                                   "flow of its middle frame with Floxels, prints EPE/Acc5/Acc10/angle error "
                                   "for dynamic and static points and the time per frame, and writes a "
                                   "bird's-eye-view PNG of points and flow vectors.")
    from floxels_ext.evaluation.simulate_cli import SCENE_NAMES  # the simulator itself is not light

    p.add_argument("--scene", default="crossing", choices=SCENE_NAMES, help="simulated scene (default crossing)")
    from floxels_ext.cli_types import nonnegative_int

    p.add_argument("--seed", type=nonnegative_int, default=0)
    p.add_argument("--scans", type=int, default=5, help="scans per window, target in the middle (default 5)")
    p.add_argument("--device", default=None, help="cpu or cuda (default: cuda if available)")
    p.add_argument("--iters", type=int, default=None, help="override the maximum number of iterations")
    p.add_argument("--small", action="store_true", help="a sparser 32-beam lidar (faster)")
    p.add_argument("--png", default="floxels_demo.png",
                   help="output picture (default floxels_demo.png; needs matplotlib, else skipped)")
    p.add_argument("--compare-reference", action="store_true",
                   help="also run the straightforward pure-PyTorch implementation and compare")
    p.set_defaults(func=run)


def prepare_demo_scans(scene: str, seed: int, num_scans: int, small: bool = False):
    """Simulated scans cropped by the paper's protocol (ground removed with the simulator's
    ground labels), plus the target's ground-truth flow and dynamic mask."""
    from floxels_ext.evaluation.protocol import protocol_mask
    from floxels_ext.evaluation.sim import simulate_sequence

    kw = dict(beams=32, azimuth_steps=512) if small else {}
    seq = simulate_sequence(scene, num_frames=num_scans, seed=seed, **kw)
    scans, target = [], num_scans // 2
    for i, fr in enumerate(seq.frames):
        keep = protocol_mask(fr.points, fr.pose[:3, 3], ground=fr.ground)
        scans.append(fr.points[keep])
        if i == target:
            gt, dyn = fr.flow[keep], fr.dynamic[keep]
    return scans, target, gt, dyn


def _print_metrics(name: str, m: dict, seconds: float) -> None:
    print(f"{name:<22} {m['dynamic_epe']:>8.4f} {m['dynamic_acc5']:>7.3f} {m['dynamic_acc10']:>7.3f} "
          f"{m['dynamic_angle']:>7.3f} | {m['static_epe']:>8.4f} {m['static_acc5']:>7.3f} "
          f"{m['static_acc10']:>7.3f} {m['static_angle']:>7.3f} | {seconds:>8.2f}")


def run(args: argparse.Namespace) -> int:
    import numpy as np
    import torch

    from floxels_ext.errors import CLIError
    from floxels_ext.estimator.config import FloxelsConfig
    from floxels_ext.estimator.api import Floxels
    from floxels_ext.evaluation.metrics import flow_metrics
    from floxels_ext.estimator.scans import resolve_device

    device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = str(resolve_device(device, None))
    except (RuntimeError, ValueError) as e:  # torch.device('gpu') raises RuntimeError
        raise CLIError(f"--device {args.device}: {e}") from None
    if not 2 <= args.scans <= 13:
        raise CLIError(f"--scans must be in [2, 13], got {args.scans}")
    if args.iters is not None and args.iters < 1:
        raise CLIError(f"--iters must be >= 1, got {args.iters}")
    verbosity = getattr(args, "verbosity", 0)  # -q: the table only; -v: also the config
    if device == "cpu":  # one thread per core stalls when other work shares the cores (cpu_threads.py)
        from floxels_ext.cpu_threads import apply_cpu_threads

        apply_cpu_threads(print if verbosity > 0 else None)
    cfg = FloxelsConfig(num_scans=args.scans)
    if args.iters is not None:
        cfg = cfg.replace(max_iters=args.iters, patience=min(cfg.patience, args.iters))
    from floxels_ext.output_paths import check_output_file

    png = check_output_file(args.png, "--png", "floxels_demo.png", suffix=".png")
    t0 = time.perf_counter()
    scans, target, gt, dyn = prepare_demo_scans(args.scene, args.seed, args.scans, args.small)
    if verbosity > 0:
        print(f"config: {cfg}")
    if verbosity >= 0:
        print(f"scene {args.scene} seed {args.seed}: {args.scans} scans simulated in {time.perf_counter() - t0:.1f} s; "
              f"target has {len(scans[target])} points ({int(dyn.sum())} dynamic) after protocol cropping")

    res = Floxels(cfg, device).fit(scans, target)
    seconds = res.timings["total"]
    m0 = flow_metrics(np.zeros_like(gt), gt, dyn)
    m = flow_metrics(res.flow, gt, dyn)
    print(f"\n{'method':<22} {'dyn EPE':>8} {'Acc5':>7} {'Acc10':>7} {'angle':>7} | {'sta EPE':>8} {'Acc5':>7} "
          f"{'Acc10':>7} {'angle':>7} | {'s/frame':>8}")
    _print_metrics("zero flow", m0, 0.0)
    _print_metrics(f"floxels_ext ({device})", m, seconds)
    if args.compare_reference:
        from floxels_ext.reference.estimator import reference_estimate_flow

        t0 = time.perf_counter()
        ref = reference_estimate_flow(scans, target, cfg, device)
        _print_metrics("pure-PyTorch reference", flow_metrics(ref, gt, dyn), time.perf_counter() - t0)
    print("(EPE in metres per frame, angle error in radians)")
    stages = ", ".join(f"{k} {v:.2f} s" for k, v in res.timings.items())
    if verbosity >= 0:
        threads = f"; {torch.get_num_threads()} CPU thread(s)" if device == "cpu" else ""
        print(f"stages: {stages}; {res.num_iters} iterations, lowest loss at {res.best_iter}{threads}")
    _picture(png, scans[target], res.flow, gt, args)
    return 0


def _picture(png: Path, points, flow, gt, args) -> None:
    """The estimate beside the ground truth (flow_plot); skipped with a note without matplotlib."""
    from floxels_ext.lidar.io import MissingDependencyError
    from floxels_ext.lidar.viz.flow_plot import plot_flow_bev

    try:
        plot_flow_bev(png, points, flow, gt_flow=gt, frame_period=0.1,
                      title=f"floxels demo: scene '{args.scene}', seed {args.seed}, {args.scans} scans "
                            f"(10 Hz lidar; boxes: moving objects, speed = median over the object)")
    except MissingDependencyError as e:
        print(f"no picture: {e}")
        return
    print(f"wrote {png}")
