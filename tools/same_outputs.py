"""Whether two `floxels run` output directories hold the same results: every frame's .npz, array
by array (names, dtypes, shapes, bytes; ``elapsed_s`` skipped: a time), and the summaries'
per-frame records. Exit 0 when identical. For changes that must not move an output byte
(issue 42/44's engine work):

    python tools/same_outputs.py OUT_BEFORE OUT_AFTER
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

SKIP = {"elapsed_s"}
SUMMARY_KEYS = ("frames", "selected", "written", "skipped", "failed", "failures", "nonfinite_rows",
                "no_points_after_crop", "far_outliers", "point_classes", "outliers", "settings")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("a", type=Path)
    ap.add_argument("b", type=Path)
    args = ap.parse_args()
    fa = sorted(p.name for p in args.a.glob("*.npz"))
    fb = sorted(p.name for p in args.b.glob("*.npz"))
    if fa != fb or not fa:
        print(f"different frame sets: {len(fa)} vs {len(fb)} files")
        return 1
    diff = 0
    for name in fa:
        with np.load(args.a / name) as za, np.load(args.b / name) as zb:
            if za.files != zb.files:
                print(f"{name}: members {za.files} vs {zb.files}")
                diff += 1
                continue
            for k in za.files:
                x, y = za[k], zb[k]
                if k not in SKIP and (x.dtype != y.dtype or x.shape != y.shape or x.tobytes() != y.tobytes()):
                    print(f"{name}: {k} differs")
                    diff += 1
    sa, sb = args.a / "run_summary.json", args.b / "run_summary.json"
    if sa.exists() and sb.exists():
        ja, jb = json.loads(sa.read_text()), json.loads(sb.read_text())
        for k in SUMMARY_KEYS:
            if ja.get(k) != jb.get(k):
                print(f"run_summary.json: {k} differs")
                diff += 1
    print(f"{len(fa)} frames, {diff} difference(s) ({', '.join(sorted(SKIP))} skipped)")
    return 1 if diff else 0


if __name__ == "__main__":
    sys.exit(main())
