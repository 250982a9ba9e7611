"""Per-iteration speed of the NSFP / FastNSF baselines on one simulated 64-beam frame:
NSFP with the fused nearest-neighbour kernel vs the chunked torch.cdist path it replaced on
CUDA, and FastNSF (DT loss), all without early stopping (fixed iteration counts).

    python bench/bench_baselines.py [--device cuda] [--iters 200] [--cdist-iters 20]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np
import torch

from floxels_ext.baselines import FastNSFConfig, NSFPConfig, fit_fastnsf, fit_nsfp
from floxels_ext.evaluation.protocol import protocol_mask
from floxels_ext.evaluation.sim import simulate_sequence


def frame_pair(scene="urban"):
    seq = simulate_sequence(scene, num_frames=2, seed=0)
    out = []
    for fr in seq.frames:
        out.append(np.ascontiguousarray(fr.points[protocol_mask(fr.points, fr.pose[:3, 3], ground=fr.ground)]))
    return out


def timed(fn, *a):
    if torch.cuda.is_available():
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    res = fn(*a)
    if torch.cuda.is_available():
        torch.cuda.synchronize()
    return res, time.perf_counter() - t0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--iters", type=int, default=200)
    ap.add_argument("--cdist-iters", type=int, default=20)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    src, tgt = frame_pair()
    dev = args.device
    print(f"frame: {len(src)} -> {len(tgt)} points, device {dev}", flush=True)
    rows = []
    cases = [("NSFP-8, fused NN kernel", fit_nsfp, NSFPConfig(max_iters=args.iters, early_stopping=False, lr=0.0008)),
             ("NSFP-8, chunked cdist (previous path)", fit_nsfp,
              NSFPConfig(max_iters=args.cdist_iters, early_stopping=False, lr=0.0008, nn_chunk_elems=1 << 27)),
             ("FastNSF-8", fit_fastnsf, FastNSFConfig(max_iters=args.iters, early_stopping=False))]
    for label, fit, cfg in cases:
        fit(src, tgt, cfg.replace(max_iters=3), dev)  # warm-up
        res, secs = timed(fit, src, tgt, cfg, dev)
        per = secs / max(res.num_iters, 1)
        rows.append({"case": label, "iters": res.num_iters, "seconds": secs, "ms_per_iter": 1e3 * per,
                     "s_per_5000_iters": 5000 * per})
        print(f"{label:40s} {res.num_iters:5d} it {secs:8.2f} s  {1e3 * per:8.2f} ms/it  "
              f"-> {5000 * per:7.1f} s per 5000 it", flush=True)
    base = next(r for r in rows if "cdist" in r["case"])["ms_per_iter"]
    print(f"NSFP speed-up of the kernel over the cdist path: {base / rows[0]['ms_per_iter']:.1f}x")
    path = args.json or os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", f"baselines_{dev}.json")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as fh:
        json.dump({"device": dev, "gpu": torch.cuda.get_device_name() if dev.startswith("cuda") else None,
                   "points": [len(src), len(tgt)], "rows": rows}, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
