"""What the evidence test keeps when it counts only what each support scan could see
(``range_mask``, ``visibility``; estimator/sight.py), on the simulator (bench/RESULTS.md, "What
each support scan could see"). Measurement only.

    python tools/sight_evidence.py classes  [--scenes urban crossing highway] [--seeds 0 1 2]
    python tools/sight_evidence.py clusters --scene urban --seed 0 --frame 5

``classes``: per scene and class, the share of the dynamic points (static: of the static points)
whose group the test explains, in 5-scan windows (frames 5-7 of 13), with the plain test, with
``range_mask`` and with ``range_mask`` + ``visibility`` (evidence "score": the flow is the same).

``clusters``: per moving DBSCAN cluster of one frame, the evidence score (mean zero-flow minus
flow residual, as the test computes it) with every scan counted, with the range images of the
kept points (as the estimator builds them) and with the simulator's ground returns added to the
range images (which preprocessing removes before the estimator sees the scans); pure PyTorch
(``reference.trilinear_gather``), CPU.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "bench"))

from floxels_ext.estimator import FloxelsConfig, estimate_sequence  # noqa: E402
from floxels_ext.estimator.distance import build_dt  # noqa: E402
from floxels_ext.estimator.sight import observed_bits, scan_sight  # noqa: E402
from floxels_ext.evaluation.protocol import protocol_mask  # noqa: E402
from floxels_ext.evaluation.sim import simulate_sequence  # noqa: E402
from floxels_ext.reference.ops import trilinear_gather  # noqa: E402

CLASSES = ((1, "car"), (2, "other vehicle"), (3, "pedestrian"), (4, "wheeled VRU"), (0, "static"))
SIGHTS = (("plain", {}), ("range_mask", {"range_mask": True}),
          ("range_mask + visibility", {"range_mask": True, "visibility": True}))


def load(scene: str, seed: int, frames: int = 13, max_range: float = 50.0):
    """Protocol-cropped scans (ground removed), their ground returns, sensors and truth."""
    seq = simulate_sequence(scene, num_frames=frames, seed=seed)
    scans, grounds, sensors, truth = [], [], [], []
    for fr in seq.frames:
        ground = fr.ground.astype(bool)
        keep = protocol_mask(fr.points, fr.pose[:3, 3], ground=ground, max_range=max_range)
        in_crop = protocol_mask(fr.points, fr.pose[:3, 3], ground=None, max_range=max_range)
        scans.append(fr.points[keep].astype(np.float32))
        grounds.append(fr.points[in_crop & ground].astype(np.float32))
        sensors.append(fr.pose[:3, 3].astype(np.float64))
        truth.append({"flow": fr.flow[keep], "classes": fr.classes[keep], "dynamic": fr.dynamic[keep].astype(bool)})
    return scans, grounds, sensors, truth


def classes(args) -> None:
    frames = [5, 6, 7]
    print("| scene | class | " + " | ".join(name for name, _ in SIGHTS) + " |\n| --- | --- |" + " ---: |" * len(SIGHTS))
    for scene, seed in zip(args.scenes, args.seeds):
        scans, _, sensors, truth = load(scene, seed)
        got = {}
        for name, extra in SIGHTS:
            out: dict = {}
            cfg = FloxelsConfig(num_scans=5, evidence="score", **extra)
            estimate_sequence(scans, cfg, frames=frames, sensor_origins=sensors, callback=out.__setitem__)
            got[name] = out
        for cls, cname in CLASSES:
            cells = []
            for name, _ in SIGHTS:
                ex = n = 0
                for f in frames:
                    t = truth[f]
                    m = (t["classes"] == cls) & (t["dynamic"] if cls else ~t["dynamic"])
                    ex += int(np.asarray(got[name][f].explained)[m].sum())
                    n += int(m.sum())
                cells.append(f"{ex / n:.3f}" if n else "-")
            print(f"| {scene} | {cname} | " + " | ".join(cells) + " |", flush=True)


def clusters(args) -> None:
    scans, grounds, sensors, truth = load(args.scene, args.seed)
    f = args.frame
    out: dict = {}
    estimate_sequence(scans, FloxelsConfig(num_scans=5, evidence="score"), frames=[f], sensor_origins=sensors,
                      callback=out.__setitem__)
    r = out[f]
    flow, lab = torch.tensor(np.asarray(r.flow)), np.asarray(r.labels)
    P, t = torch.tensor(scans[f]), truth[f]
    supports = [i for i in range(f - 2, f + 3) if i != f]
    wsum = sum(1.0 / (i - f) ** 2 for i in supports)
    sums = {k: [torch.zeros(len(P), dtype=torch.float64) for _ in range(2)] for k in ("all", "kept", "kept+ground")}
    for i in supports:
        dt, w = float(i - f), (1.0 / (i - f) ** 2) / wsum
        d = build_dt(torch.tensor(scans[i]), FloxelsConfig())
        grid = d.values[None].double()
        rf = trilinear_gather(grid, (P + dt * flow).double(), d.origin, 0.1)[:, 0].clamp_max(5.0)
        rz = trilinear_gather(grid, P.double(), d.origin, 0.1)[:, 0].clamp_max(5.0)
        kept = scan_sight(torch.tensor(scans[i]), sensors[i], band=True, image=True)
        both = scan_sight(torch.tensor(np.concatenate([scans[i], grounds[i]])), sensors[i], band=False, image=True)
        both.band = kept.band  # the kept points' band: the crop, not the ground's reach
        for key, sight in (("all", None), ("kept", kept), ("kept+ground", both)):
            m = torch.ones(len(P), dtype=torch.bool) if sight is None else observed_bits(P, [sight]).bool()
            sums[key][0] += w * m * rf
            sums[key][1] += w * m * rz
    print("| cluster | points | class | dynamic | flow (m/frame) | true | score: every scan | range images, kept points "
          "| ... + ground returns |\n| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    speed = np.linalg.norm(np.asarray(r.flow), axis=1)
    for L in np.unique(lab[lab >= 0]):
        m = lab == L
        if m.sum() < 8 or (speed[m].mean() < 0.05 and not t["dynamic"][m].any()):
            continue
        cells = []
        for rf, rz in sums.values():
            score = float(rz[m].mean() - rf[m].mean())
            kept_it = score > max(0.05 * float(rz[m].mean()), 0.02)  # FloxelsConfig's evidence margin/ratio
            cells.append(f"{score:.3f} {'kept' if kept_it else 'rejected'}")
        print(f"| {L} | {int(m.sum())} | {np.bincount(t['classes'][m]).argmax()} | {t['dynamic'][m].mean():.2f} | "
              f"{speed[m].mean():.2f} | {np.linalg.norm(t['flow'][m], axis=1).mean():.2f} | " + " | ".join(cells) + " |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("mode", choices=("classes", "clusters"))
    ap.add_argument("--scenes", nargs="+", default=["urban", "crossing", "highway"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--scene", default="urban")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--frame", type=int, default=5, help="2..10 (5-scan windows in 13 frames)")
    args = ap.parse_args(argv)
    if args.mode == "classes" and len(args.seeds) != len(args.scenes):
        ap.error("--seeds needs one seed per scene")
    if not 2 <= args.frame <= 10:
        ap.error("--frame must be in 2..10")
    (classes if args.mode == "classes" else clusters)(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
