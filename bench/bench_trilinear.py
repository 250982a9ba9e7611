"""Benchmark: floxels trilinear gather + scatter vs grid_sample forward + backward (grad to grid).

The optimiser samples a (3, Z, Y, X) flow grid at the points and splats the gradient back;
the pure-PyTorch equivalent is F.grid_sample(padding_mode="border", align_corners=True)
forward plus its backward w.r.t. the grid. Points mimic a LiDAR frame: dense near the sensor,
concentrated in a few z-slabs around the ground.
"""

from __future__ import annotations

import argparse
import json
import os

import torch
import torch.nn.functional as F

import floxels_ext  # noqa: F401
from _timing import timeit  # noqa: E402

OPS = torch.ops.floxels


def lidar_points(n, extent, z_range, device, gen):
    r = extent * torch.rand(n, generator=gen) ** 2  # density falls off with range
    a = 2 * torch.pi * torch.rand(n, generator=gen)
    z = z_range[0] + (z_range[1] - z_range[0]) * torch.rand(n, generator=gen) ** 3
    return torch.stack([r * torch.cos(a), r * torch.sin(a), z], dim=1).to(device)


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    dev = args.device
    reps = 3 if args.quick else (7 if dev == "cpu" else 50)
    sizes = [30_000] if args.quick else [30_000, 100_000, 150_000]
    C, Z, Y, X, spacing = 3, 40, 400, 400, 0.2
    origin = [-40.0, -40.0, -3.0]
    gen = torch.Generator().manual_seed(0)
    grid = torch.randn(C, Z, Y, X, generator=gen).to(dev)
    lo = torch.tensor(origin, device=dev)
    ext = torch.tensor([X - 1, Y - 1, Z - 1], device=dev, dtype=torch.float32) * spacing
    rows = []
    for n in sizes:
        pts = lidar_points(n, 40.0, (-2.5, 4.5), dev, gen)
        gout = torch.randn(n, C, generator=gen).to(dev)

        def ours():
            OPS.trilinear_gather(grid, pts, origin, spacing)
            OPS.trilinear_scatter(gout, pts, origin, spacing, [Z, Y, X])

        g5 = grid[None].clone().requires_grad_()
        norm = ((pts - lo) / ext * 2 - 1).view(1, 1, 1, n, 3)
        go5 = gout.T.reshape(1, C, 1, 1, n).contiguous()

        def baseline():
            out = F.grid_sample(g5, norm, mode="bilinear", padding_mode="border", align_corners=True)
            (gg,) = torch.autograd.grad(out, g5, go5)

        t_ours, t_base = timeit(ours, dev, reps), timeit(baseline, dev, reps)
        rows.append(dict(op="gather+scatter", n=n, grid=[C, Z, Y, X], ours_ms=t_ours, baseline_ms=t_base,
                         speedup=t_base / t_ours, baseline="grid_sample fwd+bwd(grid)"))
    print(f"device={dev} threads={torch.get_num_threads()} torch={torch.__version__}")
    print(f"{'op':<16}{'size':>10}{'ours ms':>10}{'baseline ms':>13}{'speedup':>9}")
    for r in rows:
        print(f"{r['op']:<16}{r['n']:>10}{r['ours_ms']:>10.2f}{r['baseline_ms']:>13.2f}{r['speedup']:>9.1f}")
    path = args.json or os.path.join(os.path.dirname(__file__), "results", f"trilinear_{dev}.json")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as fh:
        json.dump(dict(device=dev, threads=torch.get_num_threads(), torch=torch.__version__, rows=rows), fh, indent=1)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
