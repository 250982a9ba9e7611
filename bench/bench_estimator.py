"""End-to-end Floxels per frame: floxels_ext vs the straightforward pure-PyTorch implementation
(grid_sample look-ups, scipy EDT, sklearn DBSCAN, torch.optim.Adam) on the same simulated frames.

    python bench/bench_estimator.py [--device cpu|cuda] [--scenes crossing urban] [--quick]

Prints a table (time per frame and accuracy of both, with the dynamic EPE of answering zero
flow and each path's mean |flow|: a row where both answer zero flow is marked, its "same
accuracy" means nothing) and writes JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import numpy as np
import torch

from floxels_ext import Floxels, FloxelsConfig
from floxels_ext.evaluation.demo import prepare_demo_scans
from floxels_ext.evaluation.metrics import flow_metrics
from floxels_ext.reference.estimator import reference_estimate_flow


ZERO_FLOW = 1e-3  # m: a mean |flow| below this counts as answering zero flow


def _mean_norm(flow) -> float:
    return float(np.linalg.norm(np.nan_to_num(np.asarray(flow, np.float64)), axis=1).mean())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--scenes", nargs="+", default=["crossing", "parking"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scans", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="32-beam lidar, 100 iterations")
    ap.add_argument("--no-reference", action="store_true", help="skip the pure-PyTorch baseline")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    dev = args.device
    cfg = FloxelsConfig(num_scans=args.scans)
    if args.quick:
        cfg = cfg.replace(max_iters=100)
    rows = []
    for scene in args.scenes:
        scans, target, gt, dyn = prepare_demo_scans(scene, args.seed, args.scans, small=args.quick)
        # warm-up (first-call costs: sklearn import, kernel/JIT loads) on a tiny problem
        Floxels(cfg.replace(max_iters=2), dev).fit([s[:2000] for s in scans], target)
        res = Floxels(cfg, dev).fit(scans, target)
        m = flow_metrics(res.flow, gt, dyn)
        zero = flow_metrics(np.zeros_like(gt), gt, dyn)  # what answering "nothing moves" scores
        row = dict(scene=scene, points=int(len(scans[target])), dynamic=int(dyn.sum()), scans=args.scans,
                   zero_dyn_epe=zero["dynamic_epe"], ours_mean_flow=_mean_norm(res.flow),
                   ours_s=res.timings["total"], ours_stages=res.timings, ours_iters=res.num_iters,
                   ours_dyn_epe=m["dynamic_epe"], ours_static_epe=m["static_epe"],
                   ours_dyn_acc5=m["dynamic_acc5"], ours_dyn_acc10=m["dynamic_acc10"])
        if not args.no_reference:
            t0 = time.perf_counter()
            ref, info = reference_estimate_flow(scans, target, cfg, dev, return_info=True)
            if dev.startswith("cuda"):
                torch.cuda.synchronize()
            mr = flow_metrics(ref, gt, dyn)
            row.update(ref_s=time.perf_counter() - t0, ref_stages=info["timings"], ref_iters=len(info["losses"]),
                       ref_mean_flow=_mean_norm(ref),
                       ref_dyn_epe=mr["dynamic_epe"], ref_static_epe=mr["static_epe"],
                       ref_dyn_acc5=mr["dynamic_acc5"], ref_dyn_acc10=mr["dynamic_acc10"])
            row["speedup"] = row["ref_s"] / row["ours_s"]
        # a row where both paths answer (near) zero flow everywhere says nothing about accuracy
        row["both_zero_flow"] = bool(row["ours_mean_flow"] < ZERO_FLOW and row.get("ref_mean_flow", 0.0) < ZERO_FLOW)
        rows.append(row)

    print(f"\nFloxels end to end, {args.scans} scans, device {dev} ({platform.node()}, "
          f"{torch.get_num_threads()} threads)")
    hdr = (f"{'scene':<10} {'points':>7} {'ours s':>8} {'ref s':>8} {'speedup':>8} | {'dynEPE ours':>11} {'ref':>7} "
           f"{'zero':>7} | {'staEPE ours':>11} {'ref':>7} | {'mean|f| ours':>12} {'ref':>7}")
    print(hdr)
    print("-" * len(hdr))
    for r in rows:
        print(f"{r['scene']:<10} {r['points']:>7} {r['ours_s']:>8.2f} {r.get('ref_s', float('nan')):>8.2f} "
              f"{r.get('speedup', float('nan')):>7.1f}x | {r['ours_dyn_epe']:>11.4f} {r.get('ref_dyn_epe', float('nan')):>7.4f} "
              f"{r['zero_dyn_epe']:>7.4f} | "
              f"{r['ours_static_epe']:>11.4f} {r.get('ref_static_epe', float('nan')):>7.4f} | "
              f"{r['ours_mean_flow']:>12.4f} {r.get('ref_mean_flow', float('nan')):>7.4f}"
              + ("  <- both return zero flow: no accuracy comparison" if r["both_zero_flow"] else ""))
    for r in rows:
        st = ", ".join(f"{k} {v:.3f}" for k, v in r["ours_stages"].items())
        print(f"  {r['scene']}: ours stages [{st}]"
              + (f"; reference stages [{', '.join(f'{k} {v:.3f}' for k, v in r['ref_stages'].items())}]"
                 if "ref_stages" in r else ""))
    path = args.json or os.path.join(os.path.dirname(__file__), "results", f"estimator_{dev.split(':')[0]}.json")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as fh:
        json.dump(dict(device=dev, torch=torch.__version__, threads=torch.get_num_threads(), rows=rows), fh, indent=1)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
