"""Is the AV2 pair's slow car a property of the cost or of the data (issue 33)?

For every moving car cluster of the Argoverse 2 pair (DBSCAN of scan 0 as the estimator
runs it; a cluster counts when most of its points are dynamic car points), the cluster is
translated rigidly along its label's direction at speeds 0 .. 1.5 x the label's, and each
candidate cost of that motion is evaluated against scan 1 (moved into scan 0's frame, its
ground removed as bench/compare.py does):

* ``capped tau``: mean of min(DT_1(p + s e), tau) (tau = 1.0: the refinement's; 0.3, 0.2),
* ``capped^2 tau``: the mean squared capped residual (what the LM step minimises),
* ``GM sigma`` / ``Cauchy sigma``: Geman-McClure d^2 / (d^2 + sigma^2), Cauchy log(1 + d^2/sigma^2),
* ``trim q``: mean of the lowest fraction q of the distances (trimmed mean),
* ``sym tau``: the symmetric residual, the above forward term plus the backward one: the
  points of scan 1 near the cluster (within 1 m of the cluster swept over the candidate speeds)
  moved back by -s e onto the DT of the cluster's own points of scan 0, capped at tau
  (``sym-scan``: onto the DT of the whole scan 0).

Prints, per cluster and cost, the speed of the lowest cost and its ratio to the label's speed,
and writes the curves of the largest cluster (and a PNG of them with ``--png``). No part of the
package; the costs here are candidates, not tuned.

    PYTHONPATH=python python tools/speed_cost_curve.py [--png PATH] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
import compare  # noqa: E402

from floxels_ext.evaluation.protocol import META_CLASSES  # noqa: E402
from floxels_ext.ops import dbscan, distance_transform  # noqa: E402

F = torch.ops.floxels
CELL, PAD = 0.1, 2.0


def dt_of(points: np.ndarray):
    v, o = distance_transform(torch.from_numpy(np.ascontiguousarray(points, np.float32)), CELL, PAD)
    return v, list(o)


def lookup(dt, x: np.ndarray) -> np.ndarray:
    v, o = dt
    return F.trilinear_gather(v.unsqueeze(0), torch.from_numpy(np.ascontiguousarray(x, np.float32)), o, CELL)[:, 0].numpy()


def costs_of(d: np.ndarray) -> dict:
    """Every candidate cost of the forward distances ``d`` (m,)."""
    out = {}
    for tau in (1.0, 0.3, 0.2):
        out[f"capped {tau}"] = float(np.minimum(d, tau).mean())
    out["capped^2 1.0"] = float((np.minimum(d, 1.0) ** 2).mean())
    for s in (0.1, 0.2):
        out[f"GM {s}"] = float((d * d / (d * d + s * s)).mean())
        out[f"Cauchy {s}"] = float(np.log1p(d * d / (s * s)).mean())
    for q in (0.8, 0.5):
        k = max(1, int(round(q * len(d))))
        out[f"trim {q}"] = float(np.sort(d)[:k].mean())
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--av2", default=str(ROOT.parent / "shared" / "data" / "av2_pair" / "av2_7fab2350_pair.npz"))
    ap.add_argument("--png", default=None)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    scans, truth, _sensors = compare.load_av2_pair(args.av2)
    s0, s1, t = scans[0], scans[1], truth[0]
    car = t["dynamic"] & (np.asarray(t["classes"]) == META_CLASSES.index("car"))
    lab = dbscan(torch.from_numpy(s0), 0.5, 4).numpy()
    dt1 = dt_of(s1)
    dt0 = dt_of(s0)  # the whole target scan's DT (the symmetric residual's second form)
    print(f"{int(car.sum())} dynamic car points; clusters with most points dynamic car:")
    res = []
    for c in np.unique(lab[lab >= 0]):
        m = lab == c
        if m.sum() < 10 or car[m].mean() < 0.5:
            continue
        q = s0[m]
        v = t["flow"][m][car[m]].mean(0)
        speed = float(np.linalg.norm(v[:2]))
        e = np.array([v[0], v[1], 0.0]) / max(speed, 1e-9)
        vz = float(v[2])
        speeds = np.round(np.arange(0, 1.5 * speed + 1e-9, 0.02), 4)
        # backward term: scan-1 points near the cluster swept over the candidate speeds
        swept = np.concatenate([q + sp * e for sp in speeds[::5]])
        near1 = np.flatnonzero(np.min(np.stack([lookup(dt_of(swept), s1)]), 0) < 1.0)
        p1 = s1[near1]
        dt0c = dt_of(q)
        curves = {}
        for sp in speeds:
            u = sp * e + np.array([0, 0, vz])
            d = lookup(dt1, q + u)
            cs = costs_of(d)
            db = lookup(dt0c, p1 - u) if len(p1) else np.zeros(0)
            df = lookup(dt0, p1 - u) if len(p1) else np.zeros(0)
            for tau in (1.0, 0.3):
                cs[f"sym {tau}"] = float((np.minimum(d, tau).sum() + np.minimum(db, tau).sum())
                                         / max(len(d) + len(db), 1))
            cs["sym-scan 1.0"] = float((np.minimum(d, 1.0).sum() + np.minimum(df, 1.0).sum())
                                       / max(len(d) + len(df), 1))
            for k, val in cs.items():
                curves.setdefault(k, []).append(val)
        best = {k: float(speeds[int(np.argmin(v_))]) for k, v_ in curves.items()}
        res.append({"cluster": int(c), "points": int(m.sum()), "car_points": int(car[m].sum()),
                    "label_speed": speed, "scan1_points_near": int(len(p1)), "best": best,
                    "speeds": speeds.tolist(), "curves": curves})
    res.sort(key=lambda r: -r["car_points"])
    keys = list(res[0]["best"]) if res else []
    print("| cluster | car points | label m/frame | " + " | ".join(keys) + " |")
    print("| --- | ---: | ---: | " + " | ".join("---:" for _ in keys) + " |")
    for r in res:
        print(f"| {r['cluster']} | {r['car_points']} | {r['label_speed']:.2f} | "
              + " | ".join(f"{r['best'][k]:.2f} ({r['best'][k] / r['label_speed']:.2f})" for k in keys) + " |")
    w = np.array([r["car_points"] for r in res], float)
    print("car-point-weighted median ratio of the lowest cost's speed to the label's, per cost:")
    for k in keys:
        ratios = np.array([r["best"][k] / r["label_speed"] for r in res])
        o = np.argsort(ratios)
        cum = np.cumsum(w[o]) / w.sum()
        print(f"  {k}: {ratios[o][np.searchsorted(cum, 0.5)]:.2f}")
    if res:
        big = res[0]
        print(f"\nlargest cluster {big['cluster']} ({big['car_points']} car points, label {big['label_speed']:.2f} "
              f"m/frame), cost against speed (every 0.1 m/frame):")
        sp = np.array(big["speeds"])
        pick = [i for i, s in enumerate(sp) if abs(s * 10 - round(s * 10)) < 1e-6]
        print("| cost | " + " | ".join(f"{sp[i]:.1f}" for i in pick) + " |")
        print("| --- | " + " | ".join("---:" for _ in pick) + " |")
        for k in keys:
            cv = np.array(big["curves"][k])
            print(f"| {k} | " + " | ".join(f"{cv[i]:.3f}" for i in pick) + " |")
    if args.png and res:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        big = res[0]
        fig, ax = plt.subplots(figsize=(8, 5))
        sp = np.array(big["speeds"])
        for k in keys:
            cv = np.array(big["curves"][k])
            cv = (cv - cv.min()) / max(cv.max() - cv.min(), 1e-12)
            ax.plot(sp, cv, label=k)
        ax.axvline(big["label_speed"], color="k", ls="--", label="label")
        ax.set_xlabel("speed along the label's direction (m/frame)")
        ax.set_ylabel("cost (min-max normalised)")
        ax.set_title(f"AV2 pair, largest moving car ({big['car_points']} points)")
        ax.legend(fontsize=7)
        fig.savefig(args.png, dpi=100)
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
