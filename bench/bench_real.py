"""Label-free real-data report (issue 29): the 13 shared KITTI raw sweeps as a user runs them,
and the Argoverse 2 pair's comparison with scan 1's ground removed like scan 0's.

    python bench/bench_real.py [--device cpu|cuda] [--frames A:B] [--preset paper|accurate] [--scans N] [--work DIR]
                               [--png-dir DIR] [--no-kitti] [--no-av2] [--av2-methods floxels2 zero ...]
                               [--av2-max-points N] [--data DIR] [--poses FILE] [--json PATH]

KITTI: writes the sweeps of ``../shared/data/kitti_raw_13f`` as ``velodyne/NNNNNN.bin`` (the
data README's recipe), runs ``floxels run velodyne --odometry kiss-icp --preset paper`` (``--preset``; the
preset's window, paper 5 scans, accurate 11, unless ``--scans``) through the CLI (``--frames`` limits the estimated frames, e.g. ``0:3`` on a CPU; all 13 sweeps still serve
as odometry input and support scans) and reads every output back: per frame the shares of the
file's points that were kept (optimised), removed as ground, removed as outliers (the run
summary's ``point_classes``), the share of kept points moving (``dynamic``), the share of moving
points the motion evidence does not explain (the ``explained`` field, when the outputs carry
it; the run then uses ``--raw-flow`` so the paper's flow is what is measured; "n/a" otherwise),
and the time per frame (``elapsed_s``). A bird's-eye PNG per frame (points coloured by the
flow's direction and speed, moving objects boxed and labelled with their speed).

AV2: ``bench/compare.py``'s pair loader (scan 1's ground removed by the project's ground removal)
and its rows Floxels (2 scans), FastNSF, NSFP, plus zero flow; NSFP and FastNSF take minutes a
row on a CPU (``--av2-methods`` picks rows). Prints the tables and writes JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
SHARED = HERE.parent.parent / "shared" / "data"  # --data overrides (a device machine's copy)
sys.path.insert(0, str(HERE))


def write_kitti_bins(npz: Path, out: Path) -> Path:
    """The sweeps as KITTI .bin files (x y z reflectance, float32), as the data README says."""
    d = np.load(npz)
    o = d["frame_offsets"]
    velo = out / "velodyne"
    velo.mkdir(parents=True, exist_ok=True)
    for i in range(len(o) - 1):
        rows = np.c_[d["points"][o[i]:o[i + 1]], d["reflectance"][o[i]:o[i + 1]]].astype(np.float32)
        rows.tofile(velo / f"{i:06d}.bin")
    return velo


def _has_flag(flag: str) -> bool:
    """Whether ``floxels run`` knows ``flag`` (the motion evidence's --raw-flow is newer)."""
    import inspect

    from floxels_ext.lidar import run as run_mod

    return f'"{flag}"' in inspect.getsource(run_mod)


def kitti_report(args) -> dict:
    from floxels_ext import cli
    from floxels_ext.lidar.viz.flow_plot import plot_flow_bev
    from floxels_ext.lidar.io.outputs import read_flow_output

    work = Path(args.work)
    velo = write_kitti_bins(SHARED / "kitti_raw_13f" / "kitti_raw_2011_09_26_13f.npz", work / "kitti")
    out = work / "kitti_out"
    raw = _has_flag("--raw-flow")
    ego = ["--poses", str(Path(args.poses).resolve())] if args.poses else ["--odometry", "kiss-icp"]
    argv = ["run", str(velo), "--out", str(out), *ego, "--preset", args.preset,
            *(["--scans", str(args.scans)] if args.scans else []), "--device", args.device, "--force", "-q"]
    if args.frames:
        argv += ["--frames", args.frames]
    for o in args.option:
        argv += ["--option", o]
    if raw:
        argv.append("--raw-flow")
    print("floxels " + " ".join(argv), flush=True)
    t0 = time.perf_counter()
    rc = cli.main(argv)
    wall = time.perf_counter() - t0
    if rc != 0:
        sys.exit(f"floxels run failed (exit {rc})")
    summary = json.loads((out / "run_summary.json").read_text())
    classes = summary.get("point_classes", {})
    png_dir = Path(args.png_dir) if args.png_dir else work / "png"
    png_dir.mkdir(parents=True, exist_ok=True)
    rows = []
    for f in sorted(out.glob("[0-9]*.npz")):
        d = read_flow_output(f)
        n, kept = len(d["mask"]), int(d["mask"].sum())
        c = classes.get(f.stem, {})
        moving = d["dynamic"] & d["mask"]
        expl = d.get("explained")
        unexpl = (float((moving & ~expl).sum() / max(moving.sum(), 1)) if expl is not None else None)
        rows.append({"frame": f.stem, "points": n, "kept": kept / n, "ground": c.get("ground", 0) / n if c else None,
                     "outliers": c.get("outlier"), "moving": float(moving.sum() / max(kept, 1)),
                     "unexplained": unexpl,
                     "moving_explained": (float((moving & expl).sum() / max(kept, 1)) if expl is not None else None),
                     "s_per_frame": d.get("elapsed_s")})
        show = moving & expl if expl is not None else None
        flow = d["flow"] if show is None else np.where(show[:, None], d["flow"], 0.0)
        plot_flow_bev(png_dir / f"kitti_{f.stem}.png", d["points"], flow, mask=d["mask"], frame_period=0.1,
                      title=f"KITTI raw sweep {f.stem}: floxels run --preset {args.preset}"
                            + (f" --scans {args.scans}" if args.scans else "")
                            + (" (explained motion)" if show is not None else ""),
                      view=((-40, 40), (-40, 40)))
    return {"command": "floxels " + " ".join(argv), "raw_flow": raw, "wall_s": wall, "rows": rows,
            "summary_outliers": summary.get("outliers"), "png_dir": str(png_dir)}


def kitti_table(rep: dict) -> str:
    pct = lambda v: "n/a" if v is None else f"{100 * v:.1f} %"  # noqa: E731
    lines = ["| frame | points | kept | ground | outliers | moving (of kept) | unexplained (of moving) | s/frame |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rep["rows"]:
        lines.append(f"| {r['frame']} | {r['points']} | {pct(r['kept'])} | {pct(r['ground'])} | {r['outliers']} | "
                     f"{pct(r['moving'])} | {pct(r['unexplained'])} | "
                     f"{'n/a' if r['s_per_frame'] is None else format(r['s_per_frame'], '.2f')} |")
    mean = lambda k: (None if not rep["rows"] or any(r[k] is None for r in rep["rows"])  # noqa: E731
                      else float(np.mean([r[k] for r in rep["rows"]])))
    lines.append(f"| mean | | {pct(mean('kept'))} | {pct(mean('ground'))} | | {pct(mean('moving'))} | "
                 f"{pct(mean('unexplained'))} | {'n/a' if mean('s_per_frame') is None else format(mean('s_per_frame'), '.2f')} |")
    return "\n".join(lines)


def av2_report(args) -> dict:
    import torch

    import compare
    from floxels_ext import methods
    from floxels_ext.evaluation.metrics import evaluate_sequence

    path = SHARED / "av2_pair" / "av2_7fab2350_pair.npz"
    scans, truth, _sensors = compare.load_av2_pair(str(path), args.av2_max_points)
    d = np.load(path)
    agree = compare.ground_agreement(compare.project_ground(d["pc0"]), d["is_ground0"].astype(bool), d["pc0"])
    rows = []
    for key in args.av2_methods:
        if key == "zero":
            flow, secs, label = np.zeros_like(scans[0]), 0.0, "zero flow"
        else:
            k, label, name, opts = next(m for m in compare.METHODS if m[0] == key)
            opts = {**opts, "num_scans": 2} if name == "floxels" else dict(opts)
            label = label.replace("(5 scans)", "(2 scans)")
            preds = {}
            t0 = time.perf_counter()
            methods.get_method(name).estimate_sequence(scans, [0], args.device, opts,
                                                       lambda f, fl: preds.__setitem__(f, fl))
            if args.device.startswith("cuda"):
                torch.cuda.synchronize()
            secs, flow = time.perf_counter() - t0, np.asarray(preds[0], np.float32)
        m = evaluate_sequence([flow], [truth[0]])
        rows.append({"key": key, "label": label, "seconds": secs, "metrics": m})
        print(f"  {label}: {secs:.1f} s", flush=True)
    return {"ground_agreement_pc0": agree, "points": [len(s) for s in scans], "rows": rows,
            "device": args.device}


def av2_table(rep: dict) -> str:
    from compare_tables import main_table

    recs = [{"label": r["label"], "metrics": r["metrics"], "seconds_per_frame": r["seconds"]} for r in rep["rows"]]
    return main_table(recs)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--frames", default=None, help="KITTI frames to estimate (slice A:B; default all 13)")
    ap.add_argument("--scans", type=int, default=None, help="scans per window (default: the preset's: paper 5, "
                    "accurate 11)")
    ap.add_argument("--preset", default="paper", help="floxels run --preset (paper, accurate)")
    ap.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                    help="floxels run --option (repeatable), e.g. range_mask=no to measure an ingredient")
    ap.add_argument("--work", default=None, help="directory for the .bin files and outputs (default: a temp dir)")
    ap.add_argument("--png-dir", default=None)
    ap.add_argument("--no-kitti", action="store_true")
    ap.add_argument("--no-av2", action="store_true")
    ap.add_argument("--av2-methods", nargs="+", default=["floxels2", "fastnsf", "nsfp", "zero"],
                    choices=["floxels2", "fastnsf", "nsfp", "zero"])
    ap.add_argument("--av2-max-points", type=int, default=0)
    ap.add_argument("--json", default=str(HERE / "results" / "bench_real.json"))
    ap.add_argument("--poses", default=None, help="KITTI poses of the sweeps instead of KISS-ICP (e.g. "
                    "bench/kitti_raw_13f_poses_kiss_icp.txt, written by the KISS-ICP run of floxels run, for a machine "
                    "without kiss-icp)")
    ap.add_argument("--data", default=None, help="the shared data folder (default ../shared/data): holds "
                    "kitti_raw_13f/ and av2_pair/")
    args = ap.parse_args(argv)
    global SHARED
    if args.data:
        SHARED = Path(args.data).resolve()
    if not SHARED.is_dir():
        sys.exit(f"{SHARED} is absent: the real data lives there")
    tmp = None
    if args.work is None:
        tmp = tempfile.TemporaryDirectory(prefix="bench_real_")
        args.work = tmp.name
    res = {"device": args.device, "command": "python bench/bench_real.py " + " ".join(sys.argv[1:] if argv is None else argv)}
    if not args.no_kitti:
        res["kitti"] = kitti_report(args)
        print(f"\n## KITTI raw, 13 sweeps ({res['kitti']['command']})\n\n{kitti_table(res['kitti'])}\n"
              f"\npictures: {res['kitti']['png_dir']}", flush=True)
    if not args.no_av2:
        res["av2"] = av2_report(args)
        a = res["av2"]["ground_agreement_pc0"]
        print(f"\n## AV2 pair (2 scans, scan 1's ground removed like scan 0's; {args.device})\n\n"
              f"project ground removal on pc0 vs is_ground0: precision {a['precision']:.4f}, recall {a['recall']:.4f}\n\n"
              f"{av2_table(res['av2'])}", flush=True)
    os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
    from compare import clean

    Path(args.json).write_text(json.dumps(clean(res), indent=1, default=str) + "\n")
    print(f"\nwrote {args.json}")
    if tmp is not None and args.png_dir is None:
        print("(pictures were in the temporary --work directory; give --png-dir to keep them)")
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
