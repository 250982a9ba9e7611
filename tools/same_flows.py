"""Whether a change moved any estimate: every flow (and motion-evidence score and verdict) of the
``paper`` and ``accurate`` presets on simulated sequences and the shared AV2 pair, saved to a file,
then compared byte for byte with another checkout's or device's file. For speed work that must
not change results (issue 47's speed item):

    PYTHONPATH=python python tools/same_flows.py --out before.npz      # on the base commit
    PYTHONPATH=python python tools/same_flows.py --out after.npz --against before.npz

Each case is estimated as an API user does it (bench/_map_data.py's cases, through
``estimate_sequence`` with the sensor positions and the removed ground, bench/accurate_map.py's
``--pass origins``; the AV2 pair also with ``poses=``), the first, middle and last frame of each
sequence (``--batch-size 3``: in one group, as on CUDA). ``--iters`` caps ``max_iters`` (default 100: the steps after the optimiser see the
same kinds of flow, in a fraction of the time; 0: the presets' own). Exit status 0 when every
array is identical (dtype, shape, bytes: NaN where NaN), 1 otherwise, naming each difference.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from _map_data import SCENES, av2_case, sim_case  # noqa: E402
from accurate_map import sensor_kwargs  # noqa: E402

from floxels_ext import FloxelsConfig, estimate_sequence  # noqa: E402


def cases(args):
    for scene in args.scenes:
        for beams in args.beams:
            for length in args.lengths:
                yield sim_case(scene, args.seed, beams, length, "ends", azimuth=args.azimuth,
                               cache=Path(args.sim_cache) if args.sim_cache else None), "origins"
    if not args.no_av2:
        case = av2_case()
        yield case, "origins"
        yield case, "poses"


def estimates(args) -> dict[str, np.ndarray]:
    """Every array to compare, by name (case / preset / pass / frame / field)."""
    out = {}
    for case, how in cases(args):
        for preset in args.presets:
            cfg = FloxelsConfig.preset(preset)
            if args.iters:
                cfg = cfg.replace(max_iters=args.iters)
            t0 = time.perf_counter()
            got = {}
            estimate_sequence(case.scans, cfg, device=args.device, frames=case.frames, batch_size=args.batch_size,
                              callback=lambda f, r: got.__setitem__(f, r), **sensor_kwargs(case, cfg, how))
            for f, r in got.items():
                key = f"{case.key}/{preset}/{how}/{f}"
                out[key + "/flow"] = np.asarray(r.flow)
                if r.evidence is not None:
                    out[key + "/evidence"] = np.asarray(r.evidence)
                    out[key + "/explained"] = np.asarray(r.explained)
            print(f"{case.key} {preset} ({how}): {len(got)} frames, {time.perf_counter() - t0:.1f} s", flush=True)
    return out


def compare(a: dict, b: dict) -> int:
    """Number of arrays that differ (or are missing from either side), each named."""
    diff = 0
    for k in sorted(set(a) | set(b)):
        if k not in a or k not in b:
            print(f"{k}: only in {'the new run' if k not in a else 'the reference'}")
            diff += 1
            continue
        x, y = a[k], b[k]
        if x.dtype != y.dtype or x.shape != y.shape or x.tobytes() != y.tobytes():
            both = np.isfinite(x) & np.isfinite(y) if x.dtype.kind == "f" and x.shape == y.shape else None
            far = float(np.abs(x[both] - y[both]).max()) if both is not None and both.any() else float("nan")
            rows = int((x != y).any(axis=-1).sum()) if x.shape == y.shape and x.ndim == 2 else -1
            print(f"{k}: differs ({x.dtype}{x.shape} vs {y.dtype}{y.shape}; rows {rows}, max |diff| {far:.3g})")
            diff += 1
    print(f"{len(set(a) | set(b))} arrays compared, {diff} differ")
    return diff


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="npz written with every array")
    ap.add_argument("--against", default=None, help="npz of a reference run to compare with")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--presets", nargs="+", default=["paper", "accurate"])
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
    ap.add_argument("--beams", nargs="+", type=int, default=[32, 64])
    ap.add_argument("--lengths", nargs="+", type=int, default=[5, 11])
    ap.add_argument("--seed", type=int, default=61)
    ap.add_argument("--azimuth", type=int, default=1024)
    ap.add_argument("--iters", type=int, default=100, help="max_iters cap (0: the presets')")
    ap.add_argument("--batch-size", type=int, default=None, help="estimate_sequence's (default: the API's; the "
                    "flows must not depend on it)")
    ap.add_argument("--no-av2", action="store_true", help="leave out the shared AV2 pair")
    ap.add_argument("--sim-cache", default=str(ROOT / "bench" / "results" / "accurate_map_cache" / "sim"))
    args = ap.parse_args(argv)
    got = estimates(args)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    np.savez(args.out, **got)
    print(f"wrote {len(got)} arrays to {args.out}")
    if args.against is None:
        return 0
    with np.load(args.against) as z:
        ref = {k: z[k] for k in z.files}
    return 1 if compare(got, ref) else 0


if __name__ == "__main__":
    sys.exit(main())
