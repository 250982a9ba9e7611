"""Issue 31: speed and run-to-run noise of the CUDA path on ``bench/bench_speed.py``'s whole
frame and sequence: each is solved several times, timed, and every run's flow compared with
the first run's (bit-identical? points that differ by > 1 cm, p99.9, max). The default path
must show 0 differing points. ``--variant LABEL=NAME=VALUE ...`` adds paths that differ by
environment variables, run interleaved with the default in the same process (a host's drift
touches all alike), with their time ratio to the default.

    python bench/bench_determinism.py                      # GPU host: 128 beams, 500 iterations
    python bench/bench_determinism.py --quick              # small smoke run
    python bench/bench_determinism.py --variant "two-kernel=FLOXELS_SOLVER_PERSISTENT=0"

The before/after table of issue 31 (bench/RESULTS.md, "Determinism") came from this script
as it is at git tag ``det-with-atomic-switch`` (commit 89758de), whose build still had the
former float atomics behind an environment switch and interleaved both paths by itself: build
that commit and run ``python bench/bench_determinism.py`` there to measure them again. Prints a
table and writes bench/results/determinism_<device>.json.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(__file__))
from _timing import write_results  # noqa: E402
from bench_speed import _frames  # noqa: E402  (the same simulated frame and sequence)

from floxels_ext import Floxels, FloxelsConfig, estimate_sequence  # noqa: E402

class _Env:
    """The environment of one variant ({NAME: VALUE}) for the duration of a with block."""

    def __init__(self, env):
        self.env, self.saved = env, {}

    def __enter__(self):
        self.saved = {k: os.environ.get(k) for k in self.env}
        os.environ.update(self.env)

    def __exit__(self, *exc):
        for k, v in self.saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _sync(dev):
    if dev.startswith("cuda"):
        torch.cuda.synchronize()


def _noise(ref, other):
    """Run-to-run differences of one flow (N, 3) against the first run's."""
    d = np.linalg.norm(np.asarray(other, np.float64) - np.asarray(ref, np.float64), axis=1)
    return {"bit_identical": bool(np.asarray(ref).tobytes() == np.asarray(other).tobytes()),
            "frac_over_1cm": float((d > 0.01).mean()), "p99_9_m": float(np.quantile(d, 0.999)),
            "max_m": float(d.max())}


def _worst(noises):
    return {"bit_identical": all(n["bit_identical"] for n in noises),
            "frac_over_1cm": max(n["frac_over_1cm"] for n in noises),
            "p99_9_m": max(n["p99_9_m"] for n in noises), "max_m": max(n["max_m"] for n in noises)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--scene", default="urban")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--beams", type=int, default=128)
    ap.add_argument("--azimuth-steps", type=int, default=2048)
    ap.add_argument("--iters", type=int, default=500)
    ap.add_argument("--repeats", type=int, default=5, help="timed frames per mode (median)")
    ap.add_argument("--seq-frames", type=int, default=40)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--seq-repeats", type=int, default=3, help="timed sequence passes per mode (median)")
    ap.add_argument("--quick", action="store_true", help="32 beams, 100 iterations, short sequence")
    ap.add_argument("--variant", action="append", default=[], metavar="LABEL=NAME=VALUE[,NAME=VALUE]",
                    help="also run with these environment variables (repeatable)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    modes = {"default": {}}
    for v in args.variant:
        label, _, assigns = v.partition("=")
        modes[label] = dict(a.split("=", 1) for a in assigns.split(",") if a)
    if args.quick:
        args.beams, args.azimuth_steps, args.iters, args.seq_frames, args.repeats, args.seq_repeats = \
            32, 512, 100, 8, 2, 2
    dev = args.device
    cfg = FloxelsConfig(max_iters=args.iters, patience=10**9)  # every run does the same work
    scans, _, _ = _frames(args.scene, args.seed, max(args.seq_frames, 5), args.beams, args.azimuth_steps)
    frame, target, seq = scans[:5], 2, scans[:args.seq_frames]
    print(f"frame: {args.scene}, {args.beams} beams, points per scan {[len(s) for s in frame]}, {args.iters} "
          f"iterations; sequence {len(seq)} frames, batch {args.batch}; device {dev}", flush=True)
    for mode, env in modes.items():  # warm-up of every variant's kernels
        with _Env(env):
            Floxels(cfg.replace(max_iters=60), dev).fit(frame, target)
            estimate_sequence(seq[:6], cfg.replace(max_iters=20), device=dev, batch_size=args.batch)
    frame_s = {m: [] for m in modes}
    frame_flow = {m: [] for m in modes}
    seq_s = {m: [] for m in modes}
    seq_flow = {m: [] for m in modes}
    for _ in range(args.repeats):
        for mode, env in modes.items():
            with _Env(env):
                _sync(dev)
                t0 = time.perf_counter()
                res = Floxels(cfg, dev).fit(frame, target)
                _sync(dev)
                frame_s[mode].append(time.perf_counter() - t0)
                frame_flow[mode].append(np.asarray(res.flow))
    for _ in range(args.seq_repeats):
        for mode, env in modes.items():
            with _Env(env):
                _sync(dev)
                t0 = time.perf_counter()
                flows = estimate_sequence(seq, cfg, device=dev, batch_size=args.batch)
                _sync(dev)
                seq_s[mode].append(time.perf_counter() - t0)
                seq_flow[mode].append([np.asarray(f) for f in flows])

    out = {"device": dev, "gpu": torch.cuda.get_device_name() if dev.startswith("cuda") else "",
           "torch": torch.__version__, "points": [len(s) for s in frame], "iters": args.iters,
           "seq_frames": len(seq), "batch": args.batch, "variants": {m: e for m, e in modes.items()}, "modes": {}}
    for mode in modes:
        fn = [_noise(frame_flow[mode][0], f) for f in frame_flow[mode][1:]]
        sn = [_noise(seq_flow[mode][0][k], run[k]) for run in seq_flow[mode][1:] for k in range(len(seq))]
        out["modes"][mode] = {
            "frame_s": statistics.median(frame_s[mode]), "frame_runs_s": frame_s[mode],
            "seq_fps": len(seq) / statistics.median(seq_s[mode]), "seq_runs_s": seq_s[mode],
            "frame_noise": _worst(fn) if fn else None, "seq_noise": _worst(sn) if sn else None}
    base = out["modes"]["default"]
    for r in out["modes"].values():
        r["frame_time_vs_default"] = r["frame_s"] / base["frame_s"]
        r["seq_fps_vs_default"] = r["seq_fps"] / base["seq_fps"]

    print(f"\n{out['gpu']}: the default path" + (" and the variants, interleaved" if len(modes) > 1 else ""))
    print(f"{'path':<12} {'frame ms':>9} {'seq fr/s':>9} | run-to-run noise (worst run vs the first): "
          f"{'identical':>9} {'>1cm':>7} {'p99.9 m':>9} {'max m':>8}")
    for mode, r in out["modes"].items():
        for what in ("frame_noise", "seq_noise"):
            n = r[what] or {"bit_identical": True, "frac_over_1cm": 0.0, "p99_9_m": 0.0, "max_m": 0.0}
            lead = (f"{mode:<12} {1e3 * r['frame_s']:>9.2f} {r['seq_fps']:>9.2f}" if what == "frame_noise"
                    else " " * 32)
            print(f"{lead} | {what[:-6]:<5} {str(n['bit_identical']):>38} {100 * n['frac_over_1cm']:>6.2f}% "
                  f"{n['p99_9_m']:>9.4f} {n['max_m']:>8.4f}")
    for mode, r in out["modes"].items():
        if mode != "default":
            print(f"{mode} ({', '.join(f'{k}={v}' for k, v in modes[mode].items())}) vs default: frame time "
                  f"x{r['frame_time_vs_default']:.3f}, sequence frames/s x{r['seq_fps_vs_default']:.3f}")
    write_results(out, args.json, f"determinism_{dev.split(':')[0]}.json")


if __name__ == "__main__":
    main()
