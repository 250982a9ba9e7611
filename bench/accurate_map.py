"""Where the ``accurate`` preset loses against ``paper`` (issue 47): a map over lidar beams,
sequence lengths (windows at the sequence ends included), scene types and object speeds on the
simulator, and the shared real scans (the AV2 pair with labels; the KITTI sweeps label-free).

    python bench/accurate_map.py [--device cpu|cuda] [--beams 32 64 128] [--lengths 5 11 40]
                                 [--scenes urban crossing highway parking] [--seeds 0]
                                 [--frames ends|all|0,5,-1] [--real av2 kitti | --no-sim]
                                 [--variant LABEL=PRESET[,FIELD=VALUE...]] [--pass origins|poses|none]
                                 [--repeat N] [--cache DIR | --no-cache] [--json PATH]

Each case is estimated as an API user does it: ``estimate_sequence`` over the whole sequence
(scans in one world frame) for the scored frames, with each scan's sensor (``--pass``: its
sensor position ``sensor_origins=``, its pose ``poses=``, or nothing) and, where the preset's
``visibility`` reads it, its removed ground. Scored frames (``--frames ends``): the first, middle
and last of each sequence; at the ends a window is one-sided.

Rows (``paper`` and every ``--variant``; default ``accurate``): per beams x length over the
scenes, per scene, per frame position, all simulated frames, the AV2 pair, KITTI. Columns: mean
dynamic normalised EPE (bucketed, per class), static EPE, dynamic EPE, dynamic EPE of the fast
movers (true speed >= 1 m/frame) and the time per frame; ``LOSS`` marks a row where the variant
is worse than ``paper`` in normalised or static EPE (beyond 0.0005). Speed rows: dynamic EPE by
true speed. KITTI (no labels): the share of moving points whose DBSCAN cluster the neighbour
sweep supports no better than zero flow (bench_evidence.py's check; lower is better).

Predictions are cached (``--cache``, default bench/results/accurate_map_cache) by case, frame,
configuration, ``--pass`` and device; rows other than ``paper`` also by the estimator's source
(``paper`` is pinned by tests). Times come from the runs that computed (none on a full cache
hit): on CUDA pass ``--no-cache --repeat 3`` (median of 3 synchronised runs after a warm-up).
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _map_data import SCENES, SPEED_BUCKETS, av2_case, kitti_case, label_free_metrics, labelled_metrics, sim_case  # noqa: E402
from compare_rows import clean  # noqa: E402

from floxels_ext import FloxelsConfig, estimate_sequence  # noqa: E402

PKG = HERE.parent / "python" / "floxels_ext"
TOL = 5e-4  # a row loses where its EPE exceeds paper's by more than this (rounding of the tables)


def source_hash() -> str:
    """Hash of the estimator's and the ops' Python sources (cache key of rows other than paper)."""
    h = hashlib.sha1()
    for d in ("estimator", "ops"):
        for f in sorted((PKG / d).glob("*.py")):
            h.update(f.read_bytes())
    return h.hexdigest()[:12]


def parse_variant(text: str) -> tuple[str, FloxelsConfig]:
    """``LABEL=PRESET[,FIELD=VALUE...]`` -> (label, config)."""
    label, sep, spec = text.partition("=")
    if not sep or not label:
        raise SystemExit(f"--variant expects LABEL=PRESET[,FIELD=VALUE...], got {text!r}")
    preset, *changes = spec.split(",")
    base = FloxelsConfig.preset(preset)
    opts = dict(c.split("=", 1) for c in changes)
    return label, FloxelsConfig.from_strings(opts, base=base) if opts else base


def sensor_kwargs(case, cfg: FloxelsConfig, mode: str) -> dict:
    kw = {}
    if mode == "origins":
        kw["sensor_origins"] = case.sensors
    elif mode == "poses":
        kw["poses"] = np.stack(case.poses)
    if mode != "none" and cfg.visibility:
        kw["ground_points"] = case.ground
    return kw


def sync(dev: str) -> None:
    if dev.startswith("cuda"):
        torch.cuda.synchronize()


class Runner:
    """Flows of (case, variant) for the scored frames, from the cache or estimated (timed)."""

    def __init__(self, args):
        self.args, self.dev = args, args.device
        self.cache = None if args.no_cache else Path(args.cache)
        self.code = args.code_tag or source_hash()
        self.warm: set[str] = set()

    def key(self, case, label, cfg, frame) -> str:
        paper = cfg.replace(max_iters=FloxelsConfig.max_iters) == FloxelsConfig()
        changed = {k: v for k, v in dataclasses.asdict(cfg).items() if v != getattr(FloxelsConfig, k)}
        blob = json.dumps([case.key, frame, changed, self.args.pass_, self.dev.split(":")[0],
                           None if paper else self.code], default=str, sort_keys=True)
        return hashlib.sha1(blob.encode()).hexdigest()[:20]

    def flows(self, case, label, cfg) -> tuple[dict, float | None]:
        """({frame: flow}, seconds per computed frame or None)."""
        out, todo = {}, []
        for f in case.frames:
            p = self.cache / f"{self.key(case, label, cfg, f)}.npz" if self.cache else None
            if p is not None and p.exists():
                out[f] = np.load(p)["flow"]
            else:
                todo.append(f)
        if not todo:
            return out, None
        kw = sensor_kwargs(case, cfg, self.args.pass_)
        if self.dev.startswith("cuda") and label not in self.warm:  # every path the row takes, initialised
            estimate_sequence(case.scans, cfg, device=self.dev, frames=todo[:1], **kw)
            self.warm.add(label)
        runs, got = [], {}
        for r in range(self.args.repeat):
            res = {}
            sync(self.dev)
            t0 = time.perf_counter()
            estimate_sequence(case.scans, cfg, device=self.dev, frames=todo,
                              callback=lambda f, x: res.__setitem__(f, np.asarray(x.flow, np.float32)), **kw)
            sync(self.dev)
            runs.append(time.perf_counter() - t0)
            got = got or res
        for f, flow in got.items():
            out[f] = flow
            if self.cache:
                self.cache.mkdir(parents=True, exist_ok=True)
                np.savez(self.cache / f"{self.key(case, label, cfg, f)}.npz", flow=flow)
        return out, float(np.median(runs)) / len(todo)


def group_rows(records, labels) -> list[tuple[str, str, dict]]:
    """(group, name, {label: metrics}) rows of the table from the per-case records."""
    sim = [r for r in records if r["attrs"]["source"] == "sim"]
    groups: list[tuple[str, str, list]] = []
    for b in sorted({r["attrs"]["beams"] for r in sim}):
        for n in sorted({r["attrs"]["length"] for r in sim}):
            sel = [(r, None) for r in sim if r["attrs"]["beams"] == b and r["attrs"]["length"] == n]
            if sel:
                groups.append(("beams x length", f"{b} beams, {n} frames", sel))
    for sc in SCENES:
        sel = [(r, None) for r in sim if r["attrs"]["scene"] == sc]
        if sel:
            groups.append(("scene", sc, sel))
    for pos in ("first", "mid", "last"):
        sel = [(r, pos) for r in sim]
        groups.append(("position", pos, sel))
    if sim:
        groups.append(("all", "all simulated frames", [(r, None) for r in sim]))
    for r in records:
        if r["attrs"]["source"] != "sim":
            groups.append(("real", r["attrs"]["scene"], [(r, None)]))
    rows = []
    for g, name, sel in groups:
        row = {}
        for lab in labels:
            P, G, secs, nsec = [], [], 0.0, 0
            free = None
            for r, pos in sel:
                frames = [f for f in r["frames"] if pos is None or r["positions"][f] == pos]
                if r["truth"] is None:
                    free = r["label_free"][lab]
                    continue
                P += [r["preds"][lab][f] for f in frames]
                G += [r["truth"][f] for f in frames]
                if r["seconds"].get(lab) is not None:
                    secs, nsec = secs + r["seconds"][lab] * len(r["frames"]), nsec + len(r["frames"])
            if free is not None:
                row[lab] = {**free, "s_per_frame": secs / nsec if nsec else None}
            elif P:
                row[lab] = {**labelled_metrics(P, G), "s_per_frame": secs / nsec if nsec else None}
        if row:
            rows.append((g, name, row))
    return rows


def fmt(v, d=3):
    return "n/a" if v is None else f"{v:.{d}f}"


def table(rows, labels) -> str:
    base, others = labels[0], labels[1:]
    head = ["group", "cell"] + [f"{c} {lab}" for lab in labels for c in ("dyn norm", "static")]
    head += [f"fast dyn {lab}" for lab in labels] + [f"s/frame {lab}" for lab in labels] + ["verdict"]
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for g, name, row in rows:
        if base not in row:
            continue
        if "unsupported" in row[base]:  # label-free
            cells = [f"{100 * row[lab]['unsupported']:.1f} % unsupported" if lab in row else "" for lab in labels]
            cells = [c for lab in labels for c in (cells[labels.index(lab)], "")]
            verdict = ", ".join(f"{lab}: LOSS" for lab in others if lab in row
                                and row[lab]["unsupported"] > row[base]["unsupported"] + TOL) or "ok"
            lines.append(f"| {g} | {name} | " + " | ".join(cells + [""] * len(labels))
                         + " | " + " | ".join(fmt(row[lab].get("s_per_frame")) for lab in labels) + f" | {verdict} |")
            continue
        cells = []
        for lab in labels:
            m = row.get(lab, {})
            cells += [fmt(m.get("dyn_norm")), fmt(m.get("static"))]
        cells += [fmt(row[lab]["speed"][f"{SPEED_BUCKETS[-1][0]:g}-inf"]["epe"]) if lab in row else "" for lab in labels]
        cells += [fmt(row[lab].get("s_per_frame")) if lab in row else "" for lab in labels]
        bad = []
        for lab in others:
            if lab not in row:
                continue
            for k in ("dyn_norm", "static"):
                a, b = row[lab].get(k), row[base].get(k)
                if a is not None and b is not None and a > b + TOL:
                    bad.append(f"{lab} {k}")
        lines.append(f"| {g} | {name} | " + " | ".join(cells) + f" | {'LOSS: ' + ', '.join(bad) if bad else 'ok'} |")
    return "\n".join(lines)


def speed_table(rows, labels) -> str:
    all_row = next((row for g, _, row in rows if g == "all"), None)
    if all_row is None:
        return ""
    lines = ["| true speed (m/frame) | points | " + " | ".join(f"dyn EPE {lab}" for lab in labels) + " |",
             "|" + " --- |" * (2 + len(labels))]
    for lo, hi in SPEED_BUCKETS:
        k = f"{lo:g}-{hi:g}"
        pts = all_row[labels[0]]["speed"][k]["points"]
        lines.append(f"| {k} | {pts} | " + " | ".join(fmt(all_row[lab]["speed"][k]["epe"]) for lab in labels) + " |")
    return "\n".join(lines)


def parse_args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--beams", nargs="+", type=int, default=[32, 64, 128])
    ap.add_argument("--lengths", nargs="+", type=int, default=[5, 11, 40])
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
    ap.add_argument("--seeds", nargs="+", type=int, default=[0], help="simulator seeds, each for every scene "
                    "(tuned on 0 1 2; issue 47's held-out table: 60 61)")
    ap.add_argument("--frames", default="ends", help="scored frames: ends (first, middle, last), all, or 0,5,-1")
    ap.add_argument("--azimuth", type=int, default=2048, help="simulated lidar azimuth steps")
    ap.add_argument("--max-range", type=float, default=50.0)
    ap.add_argument("--no-sim", action="store_true", help="only the real data (--real)")
    ap.add_argument("--real", nargs="*", default=[], choices=("av2", "kitti"))
    ap.add_argument("--kitti-frames", default="ends")
    ap.add_argument("--variant", action="append", default=[], metavar="LABEL=PRESET[,FIELD=VALUE...]",
                    help="rows besides paper (default: accurate=accurate)")
    ap.add_argument("--pass", dest="pass_", choices=("origins", "poses", "none"), default="origins",
                    help="what the API gets besides the scans: sensor_origins=, poses= or nothing")
    ap.add_argument("--iters", type=int, default=None, help="max_iters of every row (smoke runs only)")
    ap.add_argument("--repeat", type=int, default=1, help="timed runs per computed case (median)")
    ap.add_argument("--cache", default=str(HERE / "results" / "accurate_map_cache"))
    ap.add_argument("--no-cache", action="store_true")
    ap.add_argument("--code-tag", default=None, help="cache key of the code of rows other than paper (default: a "
                    "hash of the estimator's and ops' sources)")
    ap.add_argument("--json", default=str(HERE / "results" / "accurate_map.json"))
    args = ap.parse_args(argv)
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        ap.error("--device cuda requested but no CUDA device is available")
    if args.repeat < 1:
        ap.error("--repeat must be >= 1")
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    variants = [("paper", FloxelsConfig())] + [parse_variant(v) for v in (args.variant or ["accurate=accurate"])]
    if args.iters:
        variants = [(lab, cfg.replace(max_iters=args.iters)) for lab, cfg in variants]
    labels = [lab for lab, _ in variants]
    runner = Runner(args)
    t_all = time.perf_counter()
    specs = [] if args.no_sim else [(sc, sd, b, n) for b in args.beams for n in args.lengths
                                    for sc in args.scenes for sd in args.seeds]
    records = []

    def run(case):
        rec = {"key": case.key, "attrs": case.attrs, "frames": case.frames, "positions": case.positions,
               "truth": case.truth and {f: case.truth[f] for f in case.frames}, "preds": {}, "seconds": {},
               "label_free": {}}
        for lab, cfg in variants:
            preds, secs = runner.flows(case, lab, cfg)
            rec["preds"][lab], rec["seconds"][lab] = preds, secs
            if case.truth is None:
                rec["label_free"][lab] = label_free_metrics(case, preds)
        records.append(rec)
        print(f"  {case.key}: frames {case.frames} [{time.perf_counter() - t_all:.0f} s]", flush=True)

    for sc, sd, b, n in specs:
        run(sim_case(sc, sd, b, n, args.frames, args.max_range, args.azimuth,
                     None if args.no_cache else Path(args.cache) / "sim"))
    if "av2" in args.real:
        run(av2_case())
    if "kitti" in args.real:
        run(kitti_case(args.kitti_frames))
    rows = group_rows(records, labels)
    print(f"\n## accurate map ({args.device}, seeds {args.seeds}, --pass {args.pass_})\n")
    print(table(rows, labels))
    print("\nDynamic EPE by true speed, all simulated frames:\n")
    print(speed_table(rows, labels))
    out = {"command": "python bench/accurate_map.py " + " ".join(sys.argv[1:] if argv is None else argv),
           "device": args.device, "gpu": torch.cuda.get_device_name() if args.device.startswith("cuda") else None,
           "host": platform.node(), "threads": torch.get_num_threads(), "code": runner.code,
           "variants": {lab: dataclasses.asdict(cfg) for lab, cfg in variants},
           "rows": [{"group": g, "cell": name, "metrics": row} for g, name, row in rows],
           "cases": [{k: r[k] for k in ("key", "attrs", "frames", "positions", "seconds")} for r in records],
           "total_seconds": time.perf_counter() - t_all}
    os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
    with open(args.json, "w") as fh:
        json.dump(clean(out), fh, indent=1, default=str)
    print(f"\nwrote {args.json} [{time.perf_counter() - t_all:.0f} s]")
    return 0


if __name__ == "__main__":
    sys.exit(main())
