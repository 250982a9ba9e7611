"""Benchmark of the fused multi-scan DT loss (forward + gradient w.r.t. flow).

Ours: torch.ops.floxels.dt_loss_fwd_bwd (one pass). Baseline, in the same run: the
pure-PyTorch equivalent built on F.grid_sample(border, align_corners=True) per scan,
forward + autograd backward (the way the loss is usually written).

Points lie on surfaces like a LiDAR sweep (a noisy ground plane and a few walls), first
in random order, then sorted by voxel index ("sorted"), which is what a caller should
do once per frame: neighbouring points then touch the same cache lines.

    python bench/bench_dt_loss.py --device cpu [--quick] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
from pathlib import Path

import torch
import torch.nn.functional as F

import floxels_ext  # noqa: E402,F401  (registers torch.ops.floxels.*)
from _timing import timeit  # noqa: E402

SPACING = 0.1
TRUNC = 2.0


def make_scene(n, dt_shape, K, device, seed=0):
    g = torch.Generator().manual_seed(seed)
    Z, Y, X = dt_shape
    # random positive fields: the access pattern, not the values, decides the speed
    dts = [(3.0 * torch.rand(Z, Y, X, generator=g)).to(device) for _ in range(K)]
    origins = []
    for k in range(K):
        origins += [-0.2 * k * SPACING, 0.1 * k * SPACING, -0.5 * SPACING]
    extent = torch.tensor([X - 1, Y - 1, Z - 1], dtype=torch.float32) * SPACING
    # LiDAR-like: 70% on a noisy ground plane, 30% on a few vertical walls (x = const)
    points = torch.rand(n, 3, generator=g) * extent
    n_ground = int(0.7 * n)
    points[:n_ground, 2] = 0.2 * extent[2] + 0.02 * torch.randn(n_ground, generator=g)
    walls = torch.rand(8, generator=g) * extent[0]
    pick = torch.randint(0, 8, (n - n_ground,), generator=g)
    points[n_ground:, 0] = walls[pick] + 0.02 * torch.randn(n - n_ground, generator=g)
    points = points[torch.randperm(n, generator=g)]  # sensor order is not spatial order
    flow = 0.05 * torch.randn(n, 3, generator=g)
    time_offsets = [1.0, -1.0, 2.0, -2.0, 3.0, -3.0][:K]
    weights = [1.0] * K
    return points.to(device), flow.to(device), dts, origins, time_offsets, weights


def sort_points(points, flow, dt_shape):
    """Orders points by the linear index of their voxel (z slowest, x fastest)."""
    Z, Y, X = dt_shape
    v = (points / SPACING).floor().long()
    key = (v[:, 2].clamp(0, Z - 1) * Y + v[:, 1].clamp(0, Y - 1)) * X + v[:, 0].clamp(0, X - 1)
    order = torch.argsort(key)
    return points[order].contiguous(), flow[order].contiguous()


def baseline_fwd_bwd(points, flow, dts, origins, time_offsets, weights):
    """grid_sample-based loss + autograd gradient (same semantics as reference.dt_loss)."""
    f = flow.detach().requires_grad_(True)
    n = points.shape[0]
    total = f.new_zeros(())
    for k, d in enumerate(dts):
        Z, Y, X = d.shape
        o = torch.tensor(origins[3 * k:3 * k + 3], dtype=f.dtype, device=f.device)
        size = torch.tensor([X - 1, Y - 1, Z - 1], dtype=f.dtype, device=f.device)
        q = (points + time_offsets[k] * f - o) / SPACING
        grid = (2.0 * q / size - 1.0).view(1, 1, 1, n, 3)
        v = F.grid_sample(d[None, None], grid, mode="bilinear", padding_mode="border", align_corners=True)
        v = v.view(n)
        v = torch.where(v < TRUNC, v, torch.zeros_like(v))
        total = total + weights[k] * v.sum() / n
    total.backward()
    return total.detach(), f.grad


def ours_fwd_bwd(points, flow, dts, origins, time_offsets, weights):
    return torch.ops.floxels.dt_loss_fwd_bwd(points, flow, dts, origins, SPACING, time_offsets, weights, TRUNC)


def graph_time(fn, calls=50, replays=20):
    """GPU time per call (ms) without host dispatch: ``calls`` calls captured into one CUDA
    graph, replayed ``replays`` times (the optimiser replays its iterations the same way)."""
    s = torch.cuda.Stream()
    s.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(s):
        for _ in range(3):
            fn()
    torch.cuda.current_stream().wait_stream(s)
    g = torch.cuda.CUDAGraph()
    with torch.cuda.graph(g):
        for _ in range(calls):
            fn()
    g.replay()
    torch.cuda.synchronize()
    a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
    a.record()
    for _ in range(replays):
        g.replay()
    b.record()
    b.synchronize()
    return a.elapsed_time(b) / (calls * replays)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", choices=["cpu", "cuda"], default="cpu")
    ap.add_argument("--quick", action="store_true", help="one small size, few repeats")
    ap.add_argument("--json", default=None, help="output JSON (default bench/results/dt_loss_<device>.json)")
    ap.add_argument("--repeats", type=int, default=None)
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    a = ap.parse_args()
    if a.threads:
        torch.set_num_threads(a.threads)
    device = a.device
    if device == "cuda" and not torch.cuda.is_available():
        sys.exit("--device cuda: no CUDA device available")
    K = 4
    if a.quick:
        sizes, dt_shape, repeats = [30_000], (20, 200, 200), a.repeats or 5
    else:
        sizes = [30_000, 100_000, 150_000]
        dt_shape = (40, 400, 400) if device == "cpu" else (60, 1000, 1000)
        repeats = a.repeats or (20 if device == "cpu" else 100)

    rows = []
    print(f"dt_loss fwd+bwd, K={K} DTs of {dt_shape}, device={device}, threads={torch.get_num_threads()}")
    print(f"{'op':<22}{'N':>8}{'order':>8}{'ours ms':>11}{'baseline ms':>13}{'speedup':>9}{'max|dloss|':>12}"
          + (f"{'graph us':>10}" if device == "cuda" else ""))
    if device == "cuda":
        print("(ours/baseline ms: events around each eager call, host dispatch included; graph us: GPU time "
              "per call from CUDA-graph replays)")
    for n in sizes:
        points, flow, dts, origins, t, w = make_scene(n, dt_shape, K, device, seed=n)
        for order in ("random", "sorted"):
            if order == "sorted":
                points, flow = sort_points(points, flow, dt_shape)
            args = (points, flow, dts, origins, t, w)
            lo, go = ours_fwd_bwd(*args)
            lb, gb = baseline_fwd_bwd(*args)
            diff = abs(float(lo) - float(lb))
            ours = timeit(lambda: ours_fwd_bwd(*args), device, repeats)
            base = timeit(lambda: baseline_fwd_bwd(*args), device, max(3, repeats // 5), warmup=1)
            row = dict(op="dt_loss_fwd_bwd", n=n, K=K, dt_shape=list(dt_shape), order=order, ours_ms=ours,
                       baseline_ms=base, speedup=base / ours, loss_abs_diff=diff,
                       grad_max_abs_diff=float((go - gb).abs().max()))
            extra = ""
            if device == "cuda":
                row["ours_graph_us"] = 1e3 * graph_time(lambda: ours_fwd_bwd(*args))
                extra = f"{row['ours_graph_us']:>10.1f}"
            rows.append(row)
            print(f"{row['op']:<22}{n:>8}{order:>8}{ours:>11.3f}{base:>13.3f}{base / ours:>8.1f}x{diff:>12.2e}{extra}")

    out = Path(a.json) if a.json else Path(__file__).resolve().parent / "results" / f"dt_loss_{device}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    meta = dict(device=device, torch=torch.__version__, threads=torch.get_num_threads(), cpu_count=os.cpu_count(),
                machine=platform.processor() or platform.machine(), quick=a.quick, repeats=repeats,
                baseline="F.grid_sample(border, align_corners=True) per scan + autograd backward",
                gpu=torch.cuda.get_device_name() if device == "cuda" else None)
    out.write_text(json.dumps(dict(meta=meta, rows=rows), indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
