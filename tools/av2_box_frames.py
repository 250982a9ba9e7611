"""Do the AV2 pair's moving cars' points agree with their labels' motion (issue 33)?

The label flow of an Argoverse 2 object is its annotated cuboid's motion. Here every moving
vehicle's points of each sweep are put into its own cuboid's frame (scan 0's points by
``box_index0``; scan 1's as the points inside ``boxes1``'s cuboid of the same track, 0.2 m
margin). If the points agreed with the label, the two sets would lie on the same surface in
the cuboid frame, and any registration of them would find a shift of 0 along the car's length.
Printed per car, each as "m/frame the points say", i.e. the label's speed plus the shift:

* ``extent 5 % / 95 %``: the 5th / 95th percentiles of the points' position along the length,
* ``NN fwd`` / ``NN sym``: the shift along the length with the lowest mean nearest-neighbour
  distance (scan 0 onto scan 1; plus scan 1 onto scan 0), searched over -0.5 .. +0.5 m,
* ``bright``: the same for the brightest points only (intensity at or above the 95th
  percentile of the car's scan-0 points: plates, lamps, reflectors, the surfaces most likely
  to be one physical spot in both sweeps).

No part of the package; a measurement of the data, not of an estimator.

    PYTHONPATH=python python tools/av2_box_frames.py [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

ROOT = Path(__file__).resolve().parents[1]
SHIFTS = np.round(np.arange(-0.5, 0.5001, 0.02), 3)


def rotation(w: float, x: float, y: float, z: float) -> np.ndarray:
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def best_shift(a: np.ndarray, b: np.ndarray, symmetric: bool) -> float | None:
    """Shift along the cuboid's length (x) of ``a`` that brings it nearest to ``b``."""
    if len(a) < 3 or len(b) < 3:
        return None
    tb, ta = cKDTree(b), cKDTree(a)
    cost = []
    for s in SHIFTS:
        u = np.array([s, 0.0, 0.0])
        d = tb.query(a + u)[0]
        if symmetric:
            d = np.concatenate([d, ta.query(b - u)[0]])
        cost.append(np.minimum(d, 0.3).mean())
    return float(SHIFTS[int(np.argmin(cost))])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--av2", default=str(ROOT.parent / "shared" / "data" / "av2_pair" / "av2_7fab2350_pair.npz"))
    ap.add_argument("--min-points", type=int, default=50)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    z = np.load(args.av2, allow_pickle=False)
    pc0, pc1 = z["pc0"].astype(np.float64), z["pc1"].astype(np.float64)
    ego0_T_ego1 = np.linalg.inv(z["ego1_T_ego0"])
    index, dynamic = z["box_index0"], z["dynamic0"]
    ids, counts = np.unique(index[dynamic & (index >= 0)], return_counts=True)
    rows = []
    for b, n in sorted(zip(ids, counts), key=lambda a: -a[1]):
        if n < args.min_points or "VEHICLE" not in str(z["categories0"][b]):
            continue
        j = np.flatnonzero(z["track_ids1"] == z["track_ids0"][b])
        if len(j) == 0:
            continue
        b0, b1 = z["boxes0"][b], z["boxes1"][j[0]]
        r0, r1 = rotation(*b0[6:10]), rotation(*b1[6:10])
        centre1 = ego0_T_ego1[:3, :3] @ b1[:3] + ego0_T_ego1[:3, 3]
        speed = float(np.linalg.norm((centre1 - b0[:3])[:2]))
        m0 = index == b
        local0 = (pc0[m0] - b0[:3]) @ r0
        local1 = (pc1 - b1[:3]) @ r1
        inside = np.all(np.abs(local1) <= b1[3:6] / 2 + 0.2, axis=1)
        local1 = local1[inside]
        i0, i1 = z["intensity0"][m0], z["intensity1"][inside]
        bright = np.percentile(i0, 95)
        q0, q1 = np.percentile(local0[:, 0], [5, 95]), np.percentile(local1[:, 0], [5, 95])
        # a shift s of scan 0's points in the cuboid frame is a speed of label + s
        says = {
            "extent 5 %": speed + float(q1[0] - q0[0]),
            "extent 95 %": speed + float(q1[1] - q0[1]),
            "NN fwd": speed + best_shift(local0, local1, False),
            "NN sym": speed + best_shift(local0, local1, True),
        }
        s = best_shift(local0[i0 >= bright], local1[i1 >= bright], False)
        says["bright"] = None if s is None else speed + s
        rows.append({"track": str(z["track_ids0"][b]), "points0": int(n), "points1": int(inside.sum()),
                     "range_m": float(np.linalg.norm(b0[:2])), "label": speed, "says": says})
    keys = list(rows[0]["says"]) if rows else []
    print("m/frame each measure of the points gives, against the label's (ratio to the label):")
    print("| vehicle points (scan 0 / 1) | range m | label | " + " | ".join(keys) + " |")
    print("| --- | ---: | ---: | " + " | ".join("---" for _ in keys) + " |")
    for r in rows:
        cells = [("-" if v is None else f"{v:.2f} ({v / r['label']:.2f})") for v in r["says"].values()]
        print(f"| {r['points0']} / {r['points1']} | {r['range_m']:.1f} | {r['label']:.2f} | " + " | ".join(cells) + " |")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
