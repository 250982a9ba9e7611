"""Issue 31: how far the CUDA flow is from the CPU flow on the same input (p50, p99.9, max
of |flow_cpu - flow_cuda| per point), on a simulated frame and on the Argoverse 2 pair, with
each path's accuracy against the ground truth, and a check that CUDA gives the same bytes
twice. Both paths are deterministic; what remains between them is explained in docs/determinism.md
("CPU against CUDA"): contracted arithmetic (fused multiply-adds on the GPU) and the order of
float sums, which Adam's sign-like first steps amplify into slightly different trajectories.

    python tools/cpu_cuda_diff.py                          # GPU host: simulator + AV2 pair
    python tools/cpu_cuda_diff.py --beams 32 --iters 150   # smaller
    python tools/cpu_cuda_diff.py --av2 /path/to/av2_7fab2350_pair.npz

Prints a table and writes bench/results/cpu_cuda_diff.json.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "bench"))
from bench_speed import _frames  # noqa: E402
from compare import load_av2_pair  # noqa: E402

from floxels_ext import FloxelsConfig, estimate_flow  # noqa: E402
from floxels_ext.evaluation.metrics import flow_metrics  # noqa: E402

AV2_DEFAULTS = (os.environ.get("FLOXELS_AV2_PAIR"), ROOT.parent / "shared/data/av2_pair/av2_7fab2350_pair.npz",
                ROOT / "shared/data/av2_pair/av2_7fab2350_pair.npz",
                Path("/work/shared/data/av2_pair/av2_7fab2350_pair.npz"))


def compare(name, scans, target, gt, dynamic, cfg):
    t0 = time.perf_counter()
    cpu = np.asarray(estimate_flow(scans, target, cfg, device="cpu"))
    t_cpu = time.perf_counter() - t0
    t0 = time.perf_counter()
    cuda = np.asarray(estimate_flow(scans, target, cfg, device="cuda"))
    torch.cuda.synchronize()
    t_cuda = time.perf_counter() - t0
    again = np.asarray(estimate_flow(scans, target, cfg, device="cuda"))
    ok = np.isfinite(cpu).all(axis=1) & np.isfinite(cuda).all(axis=1)
    d = np.linalg.norm(cpu[ok].astype(np.float64) - cuda[ok].astype(np.float64), axis=1)
    row = {"scene": name, "points": int(len(cpu)), "p50_m": float(np.quantile(d, 0.5)),
           "p99_9_m": float(np.quantile(d, 0.999)), "max_m": float(d.max()), "mean_m": float(d.mean()),
           "frac_over_1cm": float((d > 0.01).mean()), "cuda_twice_identical": cuda.tobytes() == again.tobytes(),
           "cpu_s": t_cpu, "cuda_s": t_cuda}
    if gt is not None:
        row["metrics_cpu"] = flow_metrics(cpu, gt, dynamic)
        row["metrics_cuda"] = flow_metrics(cuda, gt, dynamic)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="urban")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--beams", type=int, default=64)
    ap.add_argument("--azimuth-steps", type=int, default=2048)
    ap.add_argument("--iters", type=int, default=None, help="max iterations (default: the config's)")
    ap.add_argument("--av2", default=None, help="the Argoverse 2 pair (.npz); default: ../shared/data/av2_pair")
    ap.add_argument("--json", default=str(ROOT / "bench/results/cpu_cuda_diff.json"))
    args = ap.parse_args()
    if not torch.cuda.is_available():
        sys.exit("cpu_cuda_diff: needs a CUDA device")
    cfg = FloxelsConfig() if args.iters is None else FloxelsConfig(max_iters=args.iters)
    # warm-up (CUDA context, kernels)
    scans, gts, dyns = _frames(args.scene, args.seed, 5, args.beams, args.azimuth_steps)
    estimate_flow(scans, 2, cfg.replace(max_iters=20), device="cuda")
    rows = [compare(f"sim:{args.scene}/{args.beams}b", scans, 2, gts[2], dyns[2], cfg)]
    av2 = next((Path(p) for p in ([args.av2] if args.av2 else AV2_DEFAULTS) if p and Path(p).is_file()), None)
    if av2 is None:
        print("AV2 pair not found (--av2 PATH or FLOXELS_AV2_PAIR): simulator only", flush=True)
    else:
        s, truth, _sensors = load_av2_pair(av2)
        rows.append(compare("av2_pair", s, 0, truth[0]["flow"], truth[0]["dynamic"], cfg))
    print(f"\n|flow_cpu - flow_cuda| per point ({torch.cuda.get_device_name()}, max_iters {cfg.max_iters})")
    print(f"{'scene':<20} {'points':>7} {'p50 m':>10} {'p99.9 m':>10} {'max m':>9} {'>1cm':>7} "
          f"{'dynEPE cpu':>10} {'dynEPE cuda':>11} {'cuda twice':>10}")
    for r in rows:
        mc, mg = r.get("metrics_cpu", {}), r.get("metrics_cuda", {})
        print(f"{r['scene']:<20} {r['points']:>7} {r['p50_m']:>10.2e} {r['p99_9_m']:>10.2e} {r['max_m']:>9.4f} "
              f"{100 * r['frac_over_1cm']:>6.2f}% {mc.get('dynamic_epe', float('nan')):>10.4f} "
              f"{mg.get('dynamic_epe', float('nan')):>11.4f} {'same' if r['cuda_twice_identical'] else 'DIFFER':>10}")
    os.makedirs(os.path.dirname(args.json), exist_ok=True)
    with open(args.json, "w") as fh:
        json.dump({"gpu": torch.cuda.get_device_name(), "max_iters": cfg.max_iters, "rows": rows}, fh, indent=1,
                  default=float)
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
