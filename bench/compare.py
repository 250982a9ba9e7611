"""Floxels vs NSFP vs FastNSF on the same scans, plus the paper's Floxels ablations and the
faithfulness readings; runs split into parts (each GPU call < 10 min) and merged.

    python bench/compare.py [--device cpu|cuda] [--quick] [--dataset sim|av2]
                            [--scenes urban crossing highway] [--frames 3] [--lidar full|small]
                            [--methods floxels nsfp fastnsf ...] [--ablations none|all|GROUP...]
                            [--sim KEY=VALUE ...] [--part NAME] [--json PATH]
    python bench/compare.py --merge PART.json ... [--json merged.json] [--md tables.md]

Rows. ``--methods`` picks rows of the main table (``METHODS``: the three methods at the
paper's settings, plus NSFP's weight-decay / learning-rate readings); ``--ablations`` picks
Floxels ablation groups (``ABLATIONS``: loss, scans, voxel, es, port). Every row runs through
the method registry (``floxels_ext.methods``, as ``floxels run --method``).

Data. ``sim``: simulated lidar (``floxels_ext.evaluation.sim``; ``--lidar full`` = 64 x 1024, the
default), cropped by the paper's protocol (3 m to ``--max-range``, below 4 m, ground removed);
evaluated frames sit in the middle of each sequence so every window (up to 11 scans) is
centred on its frame. ``av2``: the real Argoverse 2 pair in ``../shared/data/av2_pair`` (or
``--av2 PATH``), all methods as two-scan estimators: scan 1 is moved into scan 0's frame
(``ego1_T_ego0``) and the label's ego flow is subtracted (object motion); non-ground points
with |x|, |y| < 35 m are evaluated (the AV2 protocol; AV2 categories mapped to the 2024
meta-classes by ``floxels_ext.evaluation.protocol.AV2_CATEGORY_MAP``, the official evaluation's ignored
categories left out), the estimators see non-ground points within 40 m: scan 0's ground is the
label's (``is_ground0``, the protocol's evaluated points), scan 1 has no label, so its ground
(and its outliers) is removed by the project's ground removal (``floxels_ext.lidar.preprocess``,
the defaults of ``floxels run``, in scan 1's own ego frame); the same removal on scan 0 matches
the label with precision and recall >= 0.97 (printed). Before issue 29 scan 1's ground was
"within 0.15 m of a labelled ground point of scan 0", which left 7,558 ground points in scan 1.

Metrics are point-weighted over all evaluated frames (``floxels_ext.evaluation.metrics.evaluate_sequence``).
Time per frame is the wall time of the method's sequence run divided by the number of
evaluated frames: per row an untimed warm-up (the first frame with the row's own options, so
every path it takes, e.g. the rigid refinement's linear solves, is initialised; ``--warmup``),
then ``--repeat`` timed runs (default 3, synchronised on CUDA), of which the median counts; the
predictions are the first run's (the accuracy figures do not depend on ``--repeat``). Each part writes its JSON
and an NPZ of every prediction and ground truth next to it; ``--merge`` recomputes the
metrics of rows split over parts (e.g. scenes) from the NPZ files and prints the tables.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

import numpy as np
import torch

from floxels_ext import methods
from floxels_ext.estimator.config import PRESETS
from floxels_ext.evaluation.protocol import AV2_CATEGORY_MAP, map_categories, protocol_mask
from floxels_ext.evaluation.sim import simulate_sequence

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from compare_tables import ablation_table, beyond_table, fmt, main_table  # noqa: E402
from compare_rows import clean, evaluate_rows, log  # noqa: E402

# Paper's baseline settings (appendix "Baseline details"): NSFP lr 0.0008, FastNSF lr 0.001,
# no weight decay, patience 100, min delta 1e-4, at most 5000 iterations.
NSFP_PAPER = {"lr": 0.0008, "weight_decay": 0.0}
# (key, label, method, options) of the main table
METHODS = [
    ("floxels", "Floxels (5 scans)", "floxels", {}),
    ("nsfp", "NSFP-8", "nsfp", NSFP_PAPER),
    ("fastnsf", "FastNSF-8", "fastnsf", {}),
    ("nsfp_wd", "NSFP-8, weight decay 1e-4", "nsfp", {**NSFP_PAPER, "weight_decay": 1e-4}),
    ("nsfp_lr8e-3", "NSFP-8, authors' code defaults (lr 0.008, weight decay 1e-4)", "nsfp", {}),
    ("fastnsf_noes", "FastNSF-8* (5000 iterations)", "fastnsf", {"early_stopping": False}),
    # two scans: the window [frame - 1, frame] (support t = -1) inside a sequence
    ("floxels2", "Floxels (2 scans)", "floxels", {"num_scans": 2}),
]
# The peer port's readings (issue 20), one at a time and together.
PORT = {"lr_milestones": (10, 20), "lr_gamma": 0.5, "patience": 20, "min_delta": 1e-4,
        "truncation_mode": "clamp", "cluster_loss_mean": "clustered"}
# The accurate preset's ingredients (a field and the fields that qualify it): the rigid
# refinement with its window limit is one ingredient
_QUALIFIERS = ("refine_max_supports", "refine_sided", "refine_search")  # fields that qualify rigid_refine
INGREDIENTS = {k: {kk: vv for kk, vv in PRESETS["accurate"].items() if kk == k or (k == "rigid_refine" and kk in _QUALIFIERS)}
               for k in PRESETS["accurate"] if k not in _QUALIFIERS}
INGREDIENTS = {(f"{k}={v[k]}" if len(v) == 1 else
                f"{k} (plain in windows <= {v['refine_max_supports']} supports"
                + (", sided beyond" if v.get("refine_sided") else "")
                + (", searched start)" if v.get("refine_search") else ")")): v
               for k, v in INGREDIENTS.items()}
# (group, label, Floxels options): the paper's ablations (Tables 2-4) and the readings
ABLATIONS = [
    ("loss", "Floxels", {}),
    ("loss", "- flow norm", {"flow_norm_loss": False}),
    ("loss", "- cluster loss", {"cluster_loss": False}),
    ("loss", "- cluster loss - flow norm", {"cluster_loss": False, "flow_norm_loss": False}),
    *[("scans", f"{n} scans", {"num_scans": n}) for n in (3, 5, 7, 9, 11)],
    *[("voxel", f"voxel {v} m", {"voxel_size": v}) for v in (0.3, 0.5, 0.7, 1.0, 2.0)],
    ("es", "baseline early stopping (5000 it, patience 100, 1e-4)",
     {"max_iters": 5000, "patience": 100, "min_delta": 1e-4}),
    ("port", "lr halved at it 10 and 20", {"lr_milestones": (10, 20), "lr_gamma": 0.5}),
    ("port", "patience 20, min delta 1e-4", {"patience": 20, "min_delta": 1e-4}),
    ("port", "truncated DT clamped at 5 m", {"truncation_mode": "clamp"}),
    ("port", "cluster loss over clustered points", {"cluster_loss_mean": "clustered"}),
    ("port", "all four port readings", PORT),
    ("port", "all four, - cluster loss", {**PORT, "cluster_loss": False}),
    # beyond the paper (issue 33): the "accurate" preset and each of its ingredients alone
    ("beyond", "paper", {}),
    ("beyond", "accurate (preset)", dict(PRESETS["accurate"])),
    *[("beyond-only", f"only {k}", v) for k, v in INGREDIENTS.items()],
    ("beyond-only", "only rigid_refine, every window", {"rigid_refine": True}),
    ("beyond-only", "only velocity_search=True (not in the preset)", {"velocity_search": True}),
    ("beyond-only", "accurate + velocity_search", {**PRESETS["accurate"], "velocity_search": True}),
    ("beyond-only", "accurate without refine_search (the preset before it)", {**PRESETS["accurate"], "refine_search": False}),
    ("beyond-only", "accurate without refine_sided", {**PRESETS["accurate"], "refine_sided": False}),
    *[("beyond-loo", f"accurate without {k}", {kk: vv for kk, vv in PRESETS["accurate"].items() if kk not in v})
      for k, v in INGREDIENTS.items()],
    ("beyond-loo", "accurate, rigid_refine plain in every window", {**PRESETS["accurate"], "refine_max_supports": 0}),
]
GROUPS = sorted({g for g, _, _ in ABLATIONS})
MAX_WINDOW = 11
SCENE_SEED = {"urban": 0, "crossing": 1, "highway": 2, "parking": 3}

def load_sim_scene(scene, seed, num_frames, lidar, max_range, max_points, sim_options):
    """Protocol-cropped scans and ground truth of one simulated sequence, and what the scans'
    sights need (:func:`_sight`): each scan's sensor position and its ground returns inside the
    protocol's crop (removed from the scan, as ``floxels run``'s preprocessing removes them)."""
    seq = simulate_sequence(scene, num_frames=num_frames, seed=seed, small=(lidar == "small"), **sim_options)
    rng = np.random.default_rng([seed, 7])
    scans, truth, sensors, grounds = [], [], [], []
    poses = [fr.pose.astype(np.float64) for fr in seq.frames]
    for fr in seq.frames:
        grounds.append(np.ascontiguousarray(
            fr.points[protocol_mask(fr.points, fr.pose[:3, 3], max_range=max_range) & fr.ground.astype(bool)],
            dtype=np.float32))
        idx = np.flatnonzero(protocol_mask(fr.points, fr.pose[:3, 3], ground=fr.ground, max_range=max_range))
        if max_points and idx.size > max_points:
            idx = np.sort(rng.choice(idx, max_points, replace=False))
        scans.append(np.ascontiguousarray(fr.points[idx], dtype=np.float32))
        truth.append({"flow": fr.flow[idx].astype(np.float32), "classes": fr.classes[idx].astype(np.int64),
                      "dynamic": fr.dynamic[idx].astype(bool)})
        sensors.append(fr.pose[:3, 3].astype(np.float64))
    return scans, truth, _sight(sensors, grounds, poses)


def _sight(sensors, grounds, poses=None) -> dict:
    """What the Floxels sights read besides the scans: ``sensors`` (each scan's sensor position),
    ``ground`` (each scan's removed ground returns, in the scans' frame) and, where known,
    ``poses`` (each scan's (4, 4) world-from-sensor matrix, for callers of ``poses=``)."""
    return {"sensors": sensors, "ground": grounds, "poses": poses}


def project_ground(points):
    """(N,) bool: ground or outlier by the project's ground removal (``floxels run``'s defaults,
    no range/height crop), ``points`` in their own ego frame (z up)."""
    from floxels_ext.lidar.preprocess import GROUND, OUTLIER, Preprocess, preprocess_classes

    cls = preprocess_classes(np.ascontiguousarray(points, np.float32),
                             Preprocess(min_range=None, max_range=None, max_height=None))
    return (cls == GROUND) | (cls == OUTLIER)


def ground_agreement(pred, label, points, box=35.0):
    """Precision and recall of a ground mask against the label, over the evaluation box."""
    sel = (np.abs(points[:, 0]) < box) & (np.abs(points[:, 1]) < box)
    tp = int((pred & label & sel).sum())
    return {"precision": tp / max(int((pred & sel).sum()), 1), "recall": tp / max(int((label & sel).sum()), 1),
            "points": int(sel.sum())}


def load_av2_pair(path, max_points=0):
    """(scans [pc0, pc1 in pc0's frame], truth of pc0 (object motion) and of pc1 (None), the
    sights' inputs (:func:`_sight`): the sensor positions [ego 0's origin, ego 1's origin in pc0's
    frame] and each scan's removed ground within the crop)."""
    d = np.load(path)
    p0, p1 = d["pc0"].astype(np.float64), d["pc1"].astype(np.float64)
    g0 = d["is_ground0"].astype(bool)
    g1 = project_ground(p1)  # in pc1's own frame, before the move into pc0's
    agree = ground_agreement(project_ground(p0), g0, p0)
    log(f"project ground removal vs is_ground0 (|x|, |y| < 35 m): precision {agree['precision']:.4f}, "
        f"recall {agree['recall']:.4f}; pc1: {int(g1.sum())} of {len(p1)} points removed as ground")
    T = np.linalg.inv(d["ego1_T_ego0"])  # ego1 -> ego0
    p1 = p1 @ T[:3, :3].T + T[:3, 3]
    box = lambda p, r: (np.abs(p[:, 0]) < r) & (np.abs(p[:, 1]) < r)  # noqa: E731
    k0 = box(p0, 40.0) & ~g0 & d["flow_valid"].astype(bool)
    k1 = box(p1, 40.0) & ~g1
    flow = (d["flow"] - d["ego_flow"]).astype(np.float32)[k0]
    # the official evaluation's meta-classes; its ignored categories (-1) count in no metric
    classes = map_categories(d["classes0"][k0], AV2_CATEGORY_MAP, "classes0")
    truth = {"flow": flow, "classes": classes, "dynamic": d["dynamic0"].astype(bool)[k0],
             "ground": ~box(p0[k0], 35.0)}  # "ground" = excluded from the metrics
    s0, s1 = p0[k0].astype(np.float32), p1[k1].astype(np.float32)
    grounds = [p[box(p, 40.0) & g].astype(np.float32) for p, g in ((p0, g0), (p1, g1))]
    if max_points:
        rng = np.random.default_rng(3)
        i0 = np.sort(rng.choice(len(s0), min(max_points, len(s0)), replace=False))
        s0, truth = s0[i0], {k: v[i0] for k, v in truth.items()}
        s1 = s1[np.sort(rng.choice(len(s1), min(max_points, len(s1)), replace=False))]
    return ([np.ascontiguousarray(s0), np.ascontiguousarray(s1)], [truth, None],
            _sight([np.zeros(3), T[:3, 3].copy()], grounds, [np.eye(4), T.copy()]))


def _sync(dev: str) -> None:
    if dev.startswith("cuda"):
        torch.cuda.synchronize()


def _same_flows(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(np.array_equal(np.asarray(a[f]), np.asarray(b[f])) for f in a)


def _sensor_kw(method, sight: dict, options: dict) -> dict:
    """``sensors=`` for methods that take it (Floxels' range_mask and visibility) and ``ground=``
    where the options read it (Floxels' visibility), as ``floxels run`` passes them."""
    kw = {"sensors": sight["sensors"]} if methods.accepts(method.estimate_sequence, "sensors") else {}
    if method.wants_ground(options):
        kw["ground"] = sight["ground"]
    return kw


def run_rows(rows, data, dev, repeat=3, warmup="full", progress=True):
    """Run every row on every scene; returns {row key: {scene: (seconds, {frame: flow}, [seconds
    of each run])}}. Per row, first an untimed warm-up on the first scene's first frame with the
    row's own options (``warmup="full"``: every code path the row takes, e.g. the rigid
    refinement's solver, is initialised before it is timed; ``"short"``: 3 iterations, which
    leaves paths that need a converged flow cold; ``"none"``), then ``repeat`` timed runs of
    each scene's sequence, synchronised on CUDA before and after; the seconds are their median
    and the predictions are the first run's (the others are checked to be the same bytes)."""
    out = {}
    for key, label, name, opts, _group in rows:
        method = methods.get_method(name)
        if warmup != "none":
            scans, _, frames, _, sight = data[0]
            w = opts if warmup == "full" else {**opts, "max_iters": 3}
            method.estimate_sequence(scans, frames[:1], dev, w, lambda f, flow, *extra: None,
                                     **_sensor_kw(method, sight, w))
            _sync(dev)
        out[key] = {}
        t_row = time.perf_counter()
        for scans, _truth, frames, scene, sight in data:
            runs, preds = [], None
            for i in range(repeat):
                got = {}
                _sync(dev)
                t0 = time.perf_counter()
                method.estimate_sequence(scans, frames, dev, opts, lambda f, flow, *extra: got.__setitem__(f, flow),
                                         **_sensor_kw(method, sight, opts))
                _sync(dev)
                runs.append(time.perf_counter() - t0)
                if preds is None:
                    preds = got
                elif not _same_flows(preds, got):
                    log(f"  note: {label}, {scene}: run {i + 1} differs from run 1 (not deterministic)")
            out[key][scene] = (float(np.median(runs)), preds, runs)
        secs = sum(s for s, *_ in out[key].values())
        nfr = sum(len(p) for _, p, _ in out[key].values())
        log(f"  {label}: {secs / max(nfr, 1):.3f} s/frame (median of {repeat}; {time.perf_counter() - t_row:.1f} s)")
    return out


def parse_args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu", help="cpu or cuda (default cpu)")
    ap.add_argument("--quick", action="store_true", help="tiny CPU smoke run")
    ap.add_argument("--dataset", choices=("sim", "av2"), default="sim")
    ap.add_argument("--av2", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..",
                                                  "shared", "data", "av2_pair", "av2_7fab2350_pair.npz"))
    ap.add_argument("--scenes", nargs="+", default=None, help="simulated scenes (default urban crossing highway)")
    ap.add_argument("--frames", type=int, default=None, help="evaluated frames per scene (default 3; quick 2)")
    ap.add_argument("--lidar", choices=("small", "full"), default=None, help="64 x 1024 (full, default) or 32 x 512")
    ap.add_argument("--max-range", type=float, default=None, help="protocol max range in m (default 50; quick 30)")
    ap.add_argument("--max-points", type=int, default=None, help="subsample each scan (0 = all; quick 1000)")
    ap.add_argument("--seeds", nargs="+", type=int, default=None,
                    help="simulator seed per scene (default urban 0, crossing 1, highway 2, parking 3; "
                         "issue 33's held-out seeds: 10 11 12)")
    ap.add_argument("--sim", nargs="+", default=[], metavar="KEY=VALUE",
                    help="extra simulate_sequence options, e.g. vehicle_detail=False range_noise=0.015")
    ap.add_argument("--methods", nargs="*", default=None, choices=[k for k, *_ in METHODS],
                    help="main-table rows (default: floxels nsfp fastnsf)")
    ap.add_argument("--ablations", nargs="*", default=None, help=f"ablation groups: none, all or of {GROUPS}")
    ap.add_argument("--iters-scale", type=float, default=1.0, help="scale every iteration limit (smoke runs)")
    ap.add_argument("--repeat", type=int, default=None,
                    help="timed runs of each row and scene; the time is their median (default 3, quick 1; 1 "
                         "for accuracy-only runs, e.g. on a loaded CPU)")
    ap.add_argument("--warmup", choices=("full", "short", "none"), default=None,
                    help="untimed run per row before timing: the first frame with the row's options (full, "
                         "default), with 3 iterations (short, the old warm-up; quick's default) or none")
    ap.add_argument("--no-npz", action="store_true", help="skip the NPZ of predictions (merge then uses the JSON metrics)")
    ap.add_argument("--part", default=None, help="name of this part (file names, merge provenance)")
    ap.add_argument("--json", default=None)
    ap.add_argument("--merge", nargs="+", default=None, metavar="PART.json", help="merge part JSONs and print tables")
    ap.add_argument("--md", default=None, help="with --merge: also write the tables (markdown) here")
    args = ap.parse_args(argv)
    if args.merge:
        return args
    q = args.quick
    args.scenes = args.scenes or (["crossing"] if q else ["urban", "crossing", "highway"])
    args.frames = args.frames or (2 if q else 3)
    args.lidar = args.lidar or ("small" if q else "full")
    args.max_range = args.max_range or (30.0 if q else 50.0)
    args.max_points = args.max_points if args.max_points is not None else (1000 if q else 0)
    args.repeat = args.repeat if args.repeat is not None else (1 if q else 3)
    args.warmup = args.warmup or ("short" if q else "full")
    args.iter_caps = {"floxels": 250, "nsfp": 250, "fastnsf": 250} if q else {}
    args.methods = ["floxels", "nsfp", "fastnsf"] if args.methods is None else args.methods
    abl = ["all"] if args.ablations is None else args.ablations
    bad = [a for a in abl if a not in GROUPS + ["all", "none"]]
    if bad:
        ap.error(f"--ablations: unknown group(s) {bad}; choose from none, all, {', '.join(GROUPS)}")
    args.ablations = [] if "none" in abl else (GROUPS if "all" in abl else abl)
    sim = {}
    for kv in args.sim:
        k, sep, v = kv.partition("=")
        if not sep:
            ap.error(f"--sim expects KEY=VALUE, got {kv!r}")
        sim[k] = {"true": True, "false": False}.get(v.lower(), v)
        if isinstance(sim[k], str):
            try:
                sim[k] = float(v) if any(c in v for c in ".e") else int(v)
            except ValueError:
                pass
    args.sim = sim
    if args.frames < 1:
        ap.error("--frames must be >= 1")
    if args.repeat < 1:
        ap.error("--repeat must be >= 1")
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        ap.error("--device cuda requested but no CUDA device is available")
    return args


def scaled(opts: dict, name: str, scale: float, caps: dict) -> dict:
    """Options with the iteration limit scaled (``--iters-scale``) and capped (``--quick``)."""
    base = {"floxels": 500, "nsfp": 5000, "fastnsf": 5000}[name]
    n = opts.get("max_iters", base)
    n = min(max(2, int(n * scale)), caps.get(name, n))
    return dict(opts) if n == opts.get("max_iters", base) else {**opts, "max_iters": n}


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.merge:
        from compare_merge import merge

        return merge(args.merge, args.json, args.md)
    dev = args.device
    t_all = time.perf_counter()
    data = []  # (scans, truth, evaluated frames, scene name, sensor positions)
    if args.dataset == "av2":
        scans, truth, sight = load_av2_pair(args.av2, args.max_points)
        data.append((scans, truth, [0], "av2_pair", sight))
        log(f"av2 pair: {len(scans[0])} / {len(scans[1])} points, {int(truth[0]['dynamic'].sum())} dynamic")
    else:
        need = max([MAX_WINDOW if "scans" in args.ablations else 5] +
                   [o.get("num_scans", 5) for g, _, o in ABLATIONS if g in args.ablations] +
                   [o.get("num_scans", 5) for k, _, n, o in METHODS if k in args.methods and n == "floxels"])
        half = need // 2
        num_frames = args.frames + 2 * half
        frames = list(range(half, half + args.frames))
        if args.seeds is not None and len(args.seeds) != len(args.scenes):
            raise SystemExit(f"--seeds needs one seed per scene ({len(args.scenes)}), got {len(args.seeds)}")
        for i, scene in enumerate(args.scenes):
            seed = SCENE_SEED.get(scene, 0) if args.seeds is None else args.seeds[i]
            scans, truth, sight = load_sim_scene(scene, seed, num_frames, args.lidar, args.max_range,
                                                 args.max_points, args.sim)
            data.append((scans, truth, frames, scene, sight))
            log(f"scene {scene}: {num_frames} scans; frames {frames}: {[len(scans[f]) for f in frames]} points "
                f"({[int(truth[f]['dynamic'].sum()) for f in frames]} dynamic) [{time.perf_counter() - t_all:.1f} s]")

    two_scan = args.dataset == "av2"
    rows = []  # (key, label, method, options, group)
    for key, label, name, opts in METHODS:
        if key in args.methods:
            o = {**opts, "num_scans": 2} if two_scan and name == "floxels" else opts
            if two_scan:
                label = label.replace("(5 scans)", "(2 scans)")
            rows.append((key, label, name, scaled(o, name, args.iters_scale, args.iter_caps), "main"))
    for group, label, opts in ABLATIONS:
        if group in args.ablations:
            if two_scan and (group == "scans" or (group.startswith("beyond") and "num_scans" in label)):
                continue  # (two-scan estimators: the window is the pair)
            o = {**opts, "num_scans": 2} if two_scan else opts
            rows.append((f"abl:{group}:{label}", label, "floxels", scaled(o, "floxels", args.iters_scale, args.iter_caps), group))

    results = run_rows(rows, data, dev, args.repeat, args.warmup)
    truth_of = {(scene, f): truth[f] for _s, truth, frames, scene, _p in data for f in frames}
    records = [{"key": k, "label": lab, "method": n, "options": o, "group": g,
                "frames": {sc: sorted(results[k][sc][1]) for sc in results[k]},
                "seconds": {sc: results[k][sc][0] for sc in results[k]},
                "seconds_runs": {sc: results[k][sc][2] for sc in results[k]}} for k, lab, n, o, g in rows]
    evaluate_rows(records, lambda k, sc, f: results[k][sc][1][f], lambda sc, f: truth_of[(sc, f)])

    pts = [len(s[f]) for s, _, fr, *_ in data for f in fr]
    title = (f"{args.dataset}: {len(data)} scene(s) x {len(pts) // max(len(data), 1)} frame(s), "
             f"{'' if two_scan else args.lidar + ' lidar, '}{np.mean(pts):.0f} points/frame, device {dev}")
    main_rows = [r for r in records if r["group"] == "main"]
    abl_rows = [r for r in records if r["group"] != "main"]
    if main_rows:
        log(f"\n## Comparison ({title})\n\n{main_table(main_rows)}")
    if abl_rows:
        log(f"\n## Floxels ablations ({title})\n\n{ablation_table(abl_rows)}")
    beyond = [r for r in records if r["group"].startswith("beyond")]
    if beyond:
        log(f"\n## Beyond the paper ({title})\n\n{beyond_table(beyond)}")

    here = os.path.dirname(os.path.abspath(__file__))
    part = args.part or f"{args.dataset}_{dev.split(':')[0]}"
    jpath = args.json or os.path.join(here, "results", f"compare_{part}.json")
    os.makedirs(os.path.dirname(os.path.abspath(jpath)), exist_ok=True)
    npz = {}
    for k, *_ in rows:
        for sc, (_, preds, _) in results[k].items():
            for f, flow in preds.items():
                npz[f"pred|{k}|{sc}|{f}"] = np.asarray(flow, np.float32)
    for (sc, f), t in truth_of.items():
        for name, v in t.items():
            npz[f"truth|{sc}|{f}|{name}"] = np.asarray(v)
    if not args.no_npz:
        np.savez_compressed(jpath[:-5] + ".npz" if jpath.endswith(".json") else jpath + ".npz", **npz)
    gpu = torch.cuda.get_device_name() if dev.startswith("cuda") else None
    meta = {"device": dev, "gpu": gpu, "host": platform.node(), "torch": torch.__version__,
            "threads": torch.get_num_threads(), "args": vars(args), "title": title, "part": part,
            "command": "python bench/compare.py " + " ".join(sys.argv[1:] if argv is None else argv),
            "total_seconds": time.perf_counter() - t_all}
    with open(jpath, "w") as fh:
        json.dump(clean({**meta, "rows": records}), fh, indent=1, default=str)
    log(f"\nwrote {jpath} (+ .npz); total {time.perf_counter() - t_all:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
