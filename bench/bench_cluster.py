"""Benchmark: floxels cluster ops vs the pure-PyTorch reference (floxels_ext.reference.ops).

Rows: cluster_mean, and the cluster-consistency loss forward + backward (ours: the fused
cluster_consistency_fwd_bwd; reference: loss + autograd backward).
"""

from __future__ import annotations

import argparse
import json
import os

import torch

import floxels_ext  # noqa: F401
from _timing import timeit  # noqa: E402
from floxels_ext.reference import ops as R

OPS = torch.ops.floxels


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    dev = args.device
    reps = 3 if args.quick else (9 if dev == "cpu" else 50)
    sizes = [(30_000, 300)] if args.quick else [(30_000, 300), (100_000, 1000), (150_000, 2000)]
    gen = torch.Generator().manual_seed(0)
    rows = []
    for n, k in sizes:
        flow = torch.randn(n, 3, generator=gen).to(dev)
        labels = torch.randint(-1, k, (n,), generator=gen).to(dev)

        def ref_fwd_bwd():
            f = flow.detach().requires_grad_()
            loss = R.cluster_consistency_loss(f, labels, k)
            (g,) = torch.autograd.grad(loss, f)

        cases = [
            ("cluster_mean", lambda: OPS.cluster_mean(flow, labels, k), lambda: R.cluster_mean(flow, labels, k)),
            ("consistency fwd+bwd", lambda: OPS.cluster_consistency_fwd_bwd(flow, labels, k), ref_fwd_bwd),
        ]
        for name, ours, ref in cases:
            t_ours, t_ref = timeit(ours, dev, reps), timeit(ref, dev, reps)
            rows.append(dict(op=name, n=n, clusters=k, ours_ms=t_ours, baseline_ms=t_ref, speedup=t_ref / t_ours,
                             baseline="floxels_ext.reference.ops (PyTorch)"))
    print(f"device={dev} threads={torch.get_num_threads()} torch={torch.__version__}")
    print(f"{'op':<22}{'size':>16}{'ours ms':>10}{'baseline ms':>13}{'speedup':>9}")
    for r in rows:
        size = f"{r['n']}/{r['clusters']}"
        print(f"{r['op']:<22}{size:>16}{r['ours_ms']:>10.3f}{r['baseline_ms']:>13.3f}{r['speedup']:>9.1f}")
    path = args.json or os.path.join(os.path.dirname(__file__), "results", f"cluster_{dev}.json")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as fh:
        json.dump(dict(device=dev, threads=torch.get_num_threads(), torch=torch.__version__, rows=rows), fh, indent=1)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
