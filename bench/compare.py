"""Floxels vs NSFP vs FastNSF on the same simulated sequences, plus the paper's Floxels ablations.

    python bench/compare.py [--device cpu|cuda] [--quick] [--scenes urban crossing] [--frames 3]
                            [--skip-ablations] [--json PATH] [--png PATH]

Every method runs through the method registry (``floxels_ext.methods``, as ``floxels run
--method``) on the same scans: simulated lidar (``floxels_ext.sim``), cropped by the paper's
protocol (3 m to ``--max-range``, below 4 m, ground removed), optionally subsampled to
``--max-points`` per scan. Evaluated frames sit in the middle of each sequence so every window
(up to 11 scans) is centred on its frame. Metrics are point-weighted over all evaluated frames
(``floxels_ext.metrics.evaluate_sequence``); time per frame is wall time of the method's whole
sequence run divided by the number of evaluated frames, after a warm-up on a tiny problem.

Prints the paper-style table (dynamic EPE/Acc5/Acc10/angle, static EPE/Acc5/Acc10, s/frame) and
the ablation table (cluster loss off, flow norm off, 3-11 scans, voxel 0.3-2.0 m), writes JSON
(default ``bench/results/compare_<device>.json``) and a PNG plot (needs matplotlib; skipped
with a message otherwise).

Sizes: the default (full) run uses the 32-beam lidar, two scenes x 3 frames, all points in
range, 5000 baseline iterations at most (early stopping as in the paper) and is meant for a
GPU (a few minutes on an H100). ``--quick`` is a CPU smoke run (under a minute on 2 cores): one
scene, 2 frames, 30 m range, 1000 points per scan, 250 iterations at most.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time

import numpy as np
import torch

from floxels_ext import methods
from floxels_ext.metrics import evaluate_sequence
from floxels_ext.protocol import protocol_mask
from floxels_ext.sim import simulate_sequence

METHODS = [("floxels", "Floxels (5 scans)"), ("nsfp", "NSFP-8"), ("fastnsf", "FastNSF-8")]

# (group, label, Floxels options) -- the paper's ablations (Tables 2, 3, 4)
ABLATIONS = [
    ("loss", "Floxels", {}),
    ("loss", "- flow norm", {"flow_norm_loss": False}),
    ("loss", "- cluster loss", {"cluster_loss": False}),
    ("loss", "- cluster loss - flow norm", {"cluster_loss": False, "flow_norm_loss": False}),
    *[("scans", f"{n} scans", {"num_scans": n}) for n in (3, 5, 7, 9, 11)],
    *[("voxel", f"voxel {v} m", {"voxel_size": v}) for v in (0.3, 0.5, 0.7, 2.0)],
]
MAX_WINDOW = 11


def log(msg: str) -> None:
    print(msg, flush=True)


def load_scene(scene: str, seed: int, num_frames: int, lidar: str, max_range: float, max_points: int):
    """Protocol-cropped scans and ground truth of one simulated sequence."""
    seq = simulate_sequence(scene, num_frames=num_frames, seed=seed, small=(lidar == "small"))
    rng = np.random.default_rng([seed, 7])
    scans, truth = [], []
    for fr in seq.frames:
        idx = np.flatnonzero(protocol_mask(fr.points, fr.pose[:3, 3], ground=fr.ground, max_range=max_range))
        if max_points and idx.size > max_points:
            idx = np.sort(rng.choice(idx, max_points, replace=False))
        scans.append(np.ascontiguousarray(fr.points[idx]))
        truth.append({"flow": fr.flow[idx], "classes": fr.classes[idx], "dynamic": fr.dynamic[idx]})
    return scans, truth


def run_method(name: str, data, device: str, options: dict, progress: bool = False):
    """Run one method on every scene; returns (metrics over all evaluated frames, s/frame)."""
    method = methods.get_method(name)
    preds, gts, seconds, nframes = [], [], 0.0, 0
    for k, (scans, truth, frames) in enumerate(data):
        out = {}
        t0 = time.perf_counter()

        def done(f, flow):
            out[f] = flow
            if progress:
                log(f"    {name}: scene {k + 1}/{len(data)} frame {f} done ({time.perf_counter() - t0:.1f} s)")

        method.estimate_sequence(scans, frames, device, options, done)
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        seconds += time.perf_counter() - t0
        nframes += len(frames)
        for f in frames:
            preds.append(out[f])
            gts.append(truth[f])
    metrics = evaluate_sequence(preds, gts)
    return metrics, seconds / nframes


def warm_up(name: str, data, device: str, options: dict) -> None:
    """First-call costs (imports such as torch.optim, CUDA context, kernel loads, allocator
    growth) on the first evaluated frame, with 3 iterations."""
    scans, _, frames = data[0]
    opts = dict(options)
    opts["max_iters"] = 3
    methods.get_method(name).estimate_sequence(scans, frames[:1], device, opts, lambda f, flow: None)


def clean(o):
    """JSON-safe copy: NaN -> None (strict JSON has no NaN), tuples -> lists."""
    if isinstance(o, float):
        return None if math.isnan(o) else o
    if isinstance(o, dict):
        return {str(k): clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [clean(v) for v in o]
    return o


def fmt(v, digits=3) -> str:
    return "n/a" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{digits}f}"


def main_table(rows) -> str:
    lines = ["| method | dyn EPE | dyn Acc5 | dyn Acc10 | dyn angle | static EPE | static Acc5 | static Acc10 | s/frame |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        m = r["metrics"]
        lines.append(f"| {r['label']} | {fmt(m['dynamic_epe'])} | {fmt(m['dynamic_acc5'])} | {fmt(m['dynamic_acc10'])} "
                     f"| {fmt(m['dynamic_angle'])} | {fmt(m['static_epe'])} | {fmt(m['static_acc5'])} "
                     f"| {fmt(m['static_acc10'])} | {fmt(r['seconds_per_frame'], 2)} |")
    return "\n".join(lines)


def ablation_table(rows) -> str:
    lines = ["| group | setting | dyn EPE | dyn Acc5 | dyn Acc10 | dyn angle | static EPE | s/frame |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        m = r["metrics"]
        lines.append(f"| {r['group']} | {r['label']} | {fmt(m['dynamic_epe'])} | {fmt(m['dynamic_acc5'])} "
                     f"| {fmt(m['dynamic_acc10'])} | {fmt(m['dynamic_angle'])} | {fmt(m['static_epe'])} "
                     f"| {fmt(r['seconds_per_frame'], 2)} |")
    return "\n".join(lines)


def plot(path: str, rows, abl_rows, title: str) -> bool:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        log("matplotlib is not installed: skipping the PNG plot")
        return False
    ncols = 2 if abl_rows else 1
    fig, axes = plt.subplots(1, ncols, figsize=(6 * ncols + (3 if abl_rows else 0), 4.5), squeeze=False)
    ax = axes[0][0]
    for r in rows:
        if r["name"] == "zero":
            continue
        t, e = r["seconds_per_frame"], r["metrics"]["dynamic_epe"]
        ax.scatter([t], [e], s=60)
        ax.annotate(r["label"], (t, e), textcoords="offset points", xytext=(5, 5))
    ax.set_xscale("log")
    ax.set_xlabel("time per frame (s, log)")
    ax.set_ylabel("dynamic EPE (m)")
    ax.set_title("accuracy vs time")
    ax.grid(True, alpha=0.3)
    if abl_rows:
        ax = axes[0][1]
        labels = [r["label"] for r in abl_rows]
        x = np.arange(len(labels))
        dyn = [r["metrics"]["dynamic_epe"] for r in abl_rows]
        sta = [r["metrics"]["static_epe"] for r in abl_rows]
        ax.bar(x - 0.2, dyn, 0.4, label="dynamic EPE")
        ax.bar(x + 0.2, sta, 0.4, label="static EPE")
        ax.set_xticks(x)
        ax.set_xticklabels(labels, rotation=60, ha="right", fontsize=8)
        ax.set_ylabel("EPE (m)")
        ax.set_title("Floxels ablations")
        ax.legend()
        ax.grid(True, axis="y", alpha=0.3)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def parse_args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu", help="cpu or cuda (default cpu)")
    ap.add_argument("--quick", action="store_true", help="tiny CPU smoke run (under a minute on 2 idle cores)")
    ap.add_argument("--scenes", nargs="+", default=None, help="simulated scenes (default: urban crossing; quick: crossing)")
    ap.add_argument("--frames", type=int, default=None, help="evaluated frames per scene (default 3; quick 2)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--lidar", choices=("small", "full"), default="small",
                    help="32 x 512 (small, default) or 64 x 1024 simulated lidar")
    ap.add_argument("--max-range", type=float, default=None, help="protocol max range in m (default 50; quick 30)")
    ap.add_argument("--max-points", type=int, default=None, help="subsample each scan to at most N points (0 = all; quick 1000)")
    ap.add_argument("--baseline-iters", type=int, default=None, help="max iterations of NSFP/FastNSF (default 5000; quick 250)")
    ap.add_argument("--floxels-iters", type=int, default=None, help="max iterations of Floxels (default 500; quick 250)")
    ap.add_argument("--methods", nargs="+", default=[m for m, _ in METHODS], choices=[m for m, _ in METHODS])
    ap.add_argument("--skip-ablations", action="store_true")
    ap.add_argument("--json", default=None)
    ap.add_argument("--png", default=None)
    args = ap.parse_args(argv)
    q = args.quick
    args.scenes = args.scenes or (["crossing"] if q else ["urban", "crossing"])
    args.frames = args.frames or (2 if q else 3)
    args.max_range = args.max_range or (30.0 if q else 50.0)
    args.max_points = args.max_points if args.max_points is not None else (1000 if q else 0)
    args.baseline_iters = args.baseline_iters or (250 if q else 5000)
    args.floxels_iters = args.floxels_iters or (250 if q else 500)
    if args.frames < 1:
        ap.error("--frames must be >= 1")
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        ap.error("--device cuda requested but no CUDA device is available")
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    dev = args.device
    t_all = time.perf_counter()
    # evaluated frames in the middle: windows of up to MAX_WINDOW scans stay centred on them
    half = MAX_WINDOW // 2 if not args.skip_ablations else 2
    num_frames = args.frames + 2 * half
    frames = list(range(half, half + args.frames))
    data = []
    for scene in args.scenes:
        scans, truth = load_scene(scene, args.seed, num_frames, args.lidar, args.max_range, args.max_points)
        data.append((scans, truth, frames))
        npts = [len(scans[f]) for f in frames]
        ndyn = [int(truth[f]["dynamic"].sum()) for f in frames]
        log(f"scene {scene}: {num_frames} scans simulated; evaluated frames {frames}: "
            f"{npts} points ({ndyn} dynamic)")

    base = {"floxels": {"max_iters": args.floxels_iters},
            "nsfp": {"max_iters": args.baseline_iters},
            "fastnsf": {"max_iters": args.baseline_iters}}
    rows = []
    zero = evaluate_sequence([np.zeros_like(t[f]["flow"]) for _, t, fr in data for f in fr],
                             [t[f] for _, t, fr in data for f in fr])
    rows.append({"name": "zero", "label": "zero flow", "metrics": zero, "seconds_per_frame": 0.0, "options": {}})
    label_of = dict(METHODS)
    for name in args.methods:
        warm_up(name, data, dev, base[name])
        t0 = time.perf_counter()
        m, spf = run_method(name, data, dev, base[name], progress=True)
        rows.append({"name": name, "label": label_of[name], "metrics": m, "seconds_per_frame": spf,
                     "options": base[name]})
        log(f"[{time.perf_counter() - t_all:6.1f} s] {label_of[name]}: dyn EPE {fmt(m['dynamic_epe'])}, "
            f"static EPE {fmt(m['static_epe'])}, {spf:.2f} s/frame ({time.perf_counter() - t0:.1f} s)")

    abl_rows = []
    if not args.skip_ablations:
        done = {}
        floxels_row = next((r for r in rows if r["name"] == "floxels"), None)
        if floxels_row is not None:  # the default configuration is the main table's Floxels row
            done[()] = (floxels_row["metrics"], floxels_row["seconds_per_frame"])
        else:
            warm_up("floxels", data, dev, base["floxels"])
        for group, label, opts in ABLATIONS:
            full = {**base["floxels"], **opts}
            # 5 scans / 0.5 m are the defaults: reuse that run
            key = tuple(sorted((k, v) for k, v in opts.items() if (k, v) not in (("num_scans", 5), ("voxel_size", 0.5))))
            if key not in done:
                done[key] = run_method("floxels", data, dev, full)
                log(f"[{time.perf_counter() - t_all:6.1f} s] ablation {label}: dyn EPE {fmt(done[key][0]['dynamic_epe'])}, "
                    f"{done[key][1]:.2f} s/frame")
            m, spf = done[key]
            abl_rows.append({"group": group, "label": label, "options": full, "metrics": m, "seconds_per_frame": spf})

    total_points = sum(len(s[f]) for s, _, fr in data for f in fr)
    title = (f"{len(args.scenes)} scene(s) x {args.frames} frame(s), {args.lidar} lidar, <= {args.max_range:g} m, "
             f"{total_points / (len(data) * args.frames):.0f} points/frame, device {dev}")
    log(f"\n## Comparison ({title})\n")
    log(main_table(rows))
    if abl_rows:
        log(f"\n## Floxels ablations ({title})\n")
        log(ablation_table(abl_rows))

    dev_tag = dev.split(":")[0]
    here = os.path.dirname(os.path.abspath(__file__))
    jpath = args.json or os.path.join(here, "results", f"compare_{dev_tag}.json")
    ppath = args.png or os.path.join(here, "results", f"compare_{dev_tag}.png")
    for p in (jpath, ppath):
        os.makedirs(os.path.dirname(os.path.abspath(p)), exist_ok=True)
    gpu = torch.cuda.get_device_name() if dev.startswith("cuda") else None
    with open(jpath, "w") as fh:
        json.dump(clean({"device": dev, "gpu": gpu, "host": platform.node(), "torch": torch.__version__,
                   "threads": torch.get_num_threads(), "args": vars(args), "title": title,
                   "frames": frames, "num_frames": num_frames, "methods": rows, "ablations": abl_rows,
                   "total_seconds": time.perf_counter() - t_all}), fh, indent=1, default=str)
    log(f"\nwrote {jpath}")
    if plot(ppath, rows, abl_rows, title):
        log(f"wrote {ppath}")
    log(f"total {time.perf_counter() - t_all:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
