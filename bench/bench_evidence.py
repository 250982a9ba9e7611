"""Motion evidence (issue 29, ``FloxelsConfig.evidence``): what it does to the accuracy on the
simulator, and what it costs per frame.

    python bench/bench_evidence.py accuracy [--device cpu] [--scenes urban crossing highway]
                                            [--seeds 0 1] [--frames 2] [--lidar small|full]
    python bench/bench_evidence.py time --device cuda [--frames 48] [--repeats 5]
    python bench/bench_evidence.py real OUT_DIR     (outputs of floxels run ... --raw-flow)
    python bench/bench_evidence.py launches [--device cpu|cuda] [--points 50000] [--supports 4]

``accuracy``: Floxels (5 scans, paper settings) on simulated sequences, evaluated
(``evaluate_sequence``: point-weighted dynamic / static EPE) with the raw flow (the paper's
output, ``evidence="off"``) and with the flow of unexplained groups zeroed, at the default
margin/ratio and at a grid of other settings (recomputed from the same optimisation through the
public API, :func:`floxels_ext.estimator.evidence.motion_evidence`, on the same distance
transforms; the default row is checked against the estimator's own ``explained``).
``time``: the same sequence estimated with ``evidence="off"`` and ``"zero"`` in alternating
repetitions in one process (``estimate_sequence``, batches of 16 on CUDA; and single frames,
``Floxels.fit``); prints the medians and the overhead in % of a frame's time.
``real``: label-free, on the outputs of a ``floxels run --raw-flow`` (e.g. the KITTI sweeps):
per frame the share of moving points (|raw flow| > the run's dynamic threshold) whose group
the evidence rejects (what the default zeroes), and an independent check of both outputs, the
raw flow and the default (unexplained groups zeroed): per DBSCAN cluster of the frame's
optimised points (eps 0.5, min 4; unclustered points alone), is the mean nearest-neighbour
distance to the next frame's optimised points (moved into this frame with the poses) with the
flow lower than with zero flow? The share of moving points in clusters where it is not (issue
29's "~21 %" measure).
``launches``: the ops (torch.profiler; top-level = dispatched from Python, all = with the ops
they call) and, on CUDA, the kernels of one ``problem_evidence`` call (the estimator's
evidence step) on a synthetic problem sorted like the solver's points.
All print a table and write JSON (``--json``, default bench/results/bench_evidence_<mode>.json).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _timing import write_results  # noqa: E402
from compare import SCENE_SEED, load_sim_scene  # noqa: E402

from floxels_ext import FloxelsConfig  # noqa: E402
from floxels_ext.estimator.api import Floxels, estimate_sequence, window_for  # noqa: E402
from floxels_ext.estimator.distance import build_dt  # noqa: E402
from floxels_ext.estimator.evidence import group_ids, motion_evidence, run_evidence  # noqa: E402
from floxels_ext.evaluation.metrics import evaluate_sequence  # noqa: E402

GRID = [(m, r) for m in (0.01, 0.02, 0.03, 0.05) for r in (0.05, 0.1, 0.15, 0.25, 0.33)]


def residuals(scans, frame, res, cfg, device, presorted_groups=False):
    """The evidence of ``frame`` as a function of (margin, ratio), on the result ``res`` and
    the DTs of its support scans (rebuilt here: a bench). ``presorted_groups``: the group ids
    computed once (timing the per-frame work of the estimator, whose points come sorted)."""
    start, stop = window_for(frame, len(scans), cfg.num_scans)
    pts = torch.as_tensor(scans[frame], device=device)
    dts, origins, offsets, weights = [], [], [], []
    for i in range(start, stop):
        if i == frame:
            continue
        d = build_dt(torch.as_tensor(scans[i], device=device), cfg)
        dts.append(d.values)
        origins.append(d.origin)
        offsets.append(float(i - frame))
        weights.append(cfg.lambda_d * cfg.time_weight(i - frame))
    labels = res.labels
    groups = group_ids(pts, labels, cfg.voxel_size, res.grid_origin)
    flow = torch.as_tensor(np.ascontiguousarray(res.flow) if isinstance(res.flow, np.ndarray) else res.flow,
                           device=device)
    if presorted_groups:  # sorted by group, as the estimator's points are: group ids from runs
        order = torch.argsort(groups)
        pts, flow, labels = pts[order], flow[order], labels[order]
        cells = group_ids(pts, None, cfg.voxel_size, res.grid_origin, presorted=False)

        def ev(margin, ratio):  # the estimator's call (problem_evidence): runs of (label, cell)
            return run_evidence(pts, flow, labels, cells, dts, origins, offsets, weights, dt_cell=cfg.dt_cell,
                                truncation=cfg.truncation, margin=margin, ratio=ratio)
        return ev
    return lambda margin, ratio: motion_evidence(pts, flow, groups, dts, origins, offsets, weights,
                                                 dt_cell=cfg.dt_cell, truncation=cfg.truncation,
                                                 margin=margin, ratio=ratio)


def accuracy(args) -> dict:
    cfg = FloxelsConfig(evidence="score")
    rows, per_frame = [], []
    preds: dict = {"raw": [], "default": [], **{f"{m}/{r}": [] for m, r in GRID}}
    truths, mismatch, sizes, dumps = [], 0, [], {}
    for scene in args.scenes:
        for seed in args.seeds:
            n_frames = 2 * (cfg.num_scans // 2) + args.frames
            scans, truth, _sensors = load_sim_scene(scene, SCENE_SEED.get(scene, 0) + 100 * seed, n_frames, args.lidar, 35.0, 0, {})
            frames = list(range(cfg.num_scans // 2, cfg.num_scans // 2 + args.frames))
            got = {}
            t0 = time.perf_counter()
            estimate_sequence(scans, cfg, device=args.device, frames=frames, callback=lambda f, r: got.__setitem__(f, r))
            secs = (time.perf_counter() - t0) / len(frames)
            for f in frames:
                res = got[f]
                ev_of = residuals(scans, f, res, cfg, args.device)
                ev = ev_of(cfg.evidence_margin, cfg.evidence_ratio)
                mismatch += int((ev.explained.cpu().numpy() != res.explained).sum())
                truths.append(truth[f])
                preds["raw"].append(res.flow)
                preds["default"].append(np.where(res.explained[:, None], res.flow, 0).astype(np.float32))
                for m, r in GRID:
                    e = ev_of(m, r).explained.cpu().numpy()
                    preds[f"{m}/{r}"].append(np.where(e[:, None], res.flow, 0).astype(np.float32))
                if args.dump:
                    dumps[f"{scene}_{seed}_{f}"] = dict(flow=res.flow, gt=truth[f]["flow"], dynamic=truth[f]["dynamic"],
                                                         classes=truth[f]["classes"],
                                                         rf=ev.residual_flow.cpu().numpy(),
                                                         rz=ev.residual_zero.cpu().numpy())
                dyn = truth[f]["dynamic"]
                per_frame.append(dict(scene=scene, seed=seed, frame=f, points=len(res.flow), s_per_frame=secs,
                                      dynamic_points=int(dyn.sum()),
                                      dynamic_unexplained=int((dyn & ~res.explained).sum()),
                                      static_explained=int((~dyn & res.explained).sum())))
                sizes.append(len(res.flow))
            print(f"{scene} seed {seed}: {len(frames)} frames, {secs:.1f} s/frame", flush=True)
    for key, P in preds.items():
        m = evaluate_sequence(P, truths)
        rows.append(dict(setting=key, dynamic_epe=m["dynamic_epe"], static_epe=m["static_epe"],
                         dynamic_acc5=m["dynamic_acc5"], static_acc5=m["static_acc5"]))
    # per scene, raw vs default
    scenes = []
    for scene in args.scenes:
        idx = [k for k, r in enumerate(per_frame) if r["scene"] == scene]
        for key in ("raw", "default"):
            m = evaluate_sequence([preds[key][k] for k in idx], [truths[k] for k in idx])
            scenes.append(dict(scene=scene, setting=key, dynamic_epe=m["dynamic_epe"], static_epe=m["static_epe"]))
    if args.dump:
        np.savez(args.dump, **{f"{k}/{n}": v for k, d in dumps.items() for n, v in d.items()})
    base = rows[0]
    print(f"\n{len(truths)} frames ({args.lidar} lidar, {statistics.mean(sizes):.0f} points/frame); "
          f"default margin {cfg.evidence_margin} m, ratio {cfg.evidence_ratio}; "
          f"estimator vs recomputed explained: {mismatch} points differ")
    print(f"{'setting (margin/ratio)':<24}{'dyn EPE':>9}{'vs raw':>8}{'static EPE':>12}{'vs raw':>8}")
    for r in rows:
        print(f"{r['setting']:<24}{r['dynamic_epe']:>9.4f}{100 * (r['dynamic_epe'] / base['dynamic_epe'] - 1):>+7.1f}%"
              f"{r['static_epe']:>12.4f}{100 * (r['static_epe'] / base['static_epe'] - 1):>+7.1f}%")
    print(f"\n{'scene':<12}{'setting':<10}{'dyn EPE':>9}{'static EPE':>12}")
    for r in scenes:
        print(f"{r['scene']:<12}{r['setting']:<10}{r['dynamic_epe']:>9.4f}{r['static_epe']:>12.4f}")
    return dict(rows=rows, scenes=scenes, frames=per_frame, mismatch=mismatch,
                margin=cfg.evidence_margin, ratio=cfg.evidence_ratio)


def timing(args) -> dict:
    dev = args.device
    n_frames = args.frames + 4
    scans, _, _sensors = load_sim_scene("urban", 0, n_frames, args.lidar, 35.0, 0, {})
    if dev.startswith("cuda"):
        scans = [torch.as_tensor(s, device=dev) for s in scans]  # uploads out of the timing
    frames = list(range(2, 2 + args.frames))
    cfgs = {mode: FloxelsConfig(evidence=mode) for mode in ("off", "zero")}

    def sync():
        if dev.startswith("cuda"):
            torch.cuda.synchronize()

    def run_seq(cfg):
        sync()
        t0 = time.perf_counter()
        estimate_sequence(scans, cfg, device=dev, frames=frames)
        sync()
        return (time.perf_counter() - t0) / len(frames)

    def run_one(cfg):
        sync()
        t0 = time.perf_counter()
        Floxels(cfg, dev).fit(scans[:5], 2)
        sync()
        return time.perf_counter() - t0

    for cfg in cfgs.values():  # warm-up
        run_seq(cfg)
        run_one(cfg)
    seq = {m: [] for m in cfgs}
    one = {m: [] for m in cfgs}
    for _ in range(args.repeats):  # alternating, so drifts of the machine hit both
        for m, cfg in cfgs.items():
            seq[m].append(run_seq(cfg))
            one[m].append(run_one(cfg))
    out = {}
    print(f"{'workload':<34}{'off ms/frame':>14}{'zero ms/frame':>15}{'overhead':>10}")
    for name, d in (("estimate_sequence (batches)", seq), ("single frame (Floxels.fit)", one)):
        a, b = statistics.median(d["off"]), statistics.median(d["zero"])
        out[name] = dict(off_ms=1e3 * a, zero_ms=1e3 * b, overhead_pct=100 * (b / a - 1),
                         off_all_ms=[1e3 * x for x in d["off"]], zero_all_ms=[1e3 * x for x in d["zero"]])
        print(f"{name:<34}{1e3 * a:>14.2f}{1e3 * b:>15.2f}{100 * (b / a - 1):>+9.1f}%")
    # the evidence step alone on one frame (its DT look-ups and segment sums; CUDA events), as
    # a share of the batched frame time above
    from _timing import timeit

    res = Floxels(cfgs["off"], dev).fit(scans[:5], 2)
    ev_of = residuals(scans, 2, res, cfgs["off"], dev, presorted_groups=True)
    ms = timeit(lambda: ev_of(0.03, 0.25), "cuda" if dev.startswith("cuda") else "cpu", repeats=20)
    a = out["estimate_sequence (batches)"]["off_ms"]
    out["evidence_step_ms"] = ms
    out["evidence_step_pct_of_batched_frame"] = 100 * ms / a
    print(f"{'evidence step alone (one frame)':<34}{ms:>14.3f} ms = {100 * ms / a:.1f}% of a batched frame")
    out["points_per_frame"] = float(np.mean([len(s) for s in scans]))
    return out


def next_scan_check(points, flow, moving, nxt, labels) -> int:
    """Moving points in clusters whose flow does not bring them closer to the next scan
    ``nxt`` (nearest-neighbour distance, cluster mean) than zero flow does."""
    from scipy.spatial import cKDTree

    tree = cKDTree(nxt)
    d_flow = tree.query(points + flow)[0]
    d_zero = tree.query(points)[0]
    groups = np.where(labels >= 0, labels, labels.max() + 1 + np.arange(len(labels)))
    _, g = np.unique(groups, return_inverse=True)
    cnt = np.bincount(g)
    worse = np.bincount(g, d_flow) / cnt >= np.bincount(g, d_zero) / cnt
    return int((moving & worse[g]).sum())


def real(args) -> dict:
    from floxels_ext.lidar.io.outputs import read_flow_output, run_outputs
    from floxels_ext.ops import dbscan

    files = run_outputs(args.out_dir)
    outs = [read_flow_output(f) for f in files]
    rows = []
    for k, d in enumerate(outs):
        if d["explained"] is None:
            raise SystemExit(f"{files[k]}: no motion evidence (run floxels run with --raw-flow, not evidence=off)")
        if d["settings"].get("options", {}).get("evidence") != "score":
            raise SystemExit(f"{files[k]}: written without --raw-flow (the raw flow is needed)")
        m = d["mask"]
        P, raw, ex = d["points"][m], d["flow"][m], d["explained"][m]
        thr = float(d["settings"].get("dynamic_threshold", 0.05))
        moving = np.linalg.norm(raw, axis=1) > thr
        row = dict(frame=files[k].stem, optimised=int(m.sum()), moving=int(moving.sum()),
                   moving_unexplained=int((moving & ~ex).sum()))
        zeroed = np.where(ex[:, None], raw, 0)
        moving_z = np.linalg.norm(zeroed, axis=1) > thr
        row["moving_after"] = int(moving_z.sum())
        if k + 1 < len(outs):
            nd = outs[k + 1]
            T = np.linalg.solve(d["pose"], nd["pose"])  # next frame -> this frame
            q = nd["points"][nd["mask"]].astype(np.float64) @ T[:3, :3].T + T[:3, 3]
            labels = dbscan(torch.as_tensor(P), 0.5, 4).numpy()
            row["raw_not_better_than_zero"] = next_scan_check(P, raw, moving, q, labels)
            row["default_not_better_than_zero"] = next_scan_check(P, zeroed, moving_z, q, labels)
        rows.append(row)
    tot = {key: sum(r.get(key, 0) for r in rows) for key in ("moving", "moving_unexplained", "moving_after")}
    checked = [r for r in rows if "raw_not_better_than_zero" in r]
    mv_c = sum(r["moving"] for r in checked)
    mvz_c = sum(r["moving_after"] for r in checked)
    raw_bad = sum(r["raw_not_better_than_zero"] for r in checked)
    def_bad = sum(r["default_not_better_than_zero"] for r in checked)
    print(f"{'frame':<10}{'optimised':>10}{'moving':>8}{'rejected':>10}{'moving after':>14}"
          f"{'raw: next scan not better':>27}{'default: idem':>15}")
    def pct(a, b):
        return "" if a is None else f"{100 * a / max(b, 1):.1f}%"

    for r in rows:
        print(f"{r['frame']:<10}{r['optimised']:>10}{r['moving']:>8}{pct(r['moving_unexplained'], r['moving']):>10}"
              f"{r['moving_after']:>14}{pct(r.get('raw_not_better_than_zero'), r['moving']):>27}"
              f"{pct(r.get('default_not_better_than_zero'), r['moving_after']):>15}")
    summary = dict(moving=tot["moving"], rejected_share=tot["moving_unexplained"] / max(tot["moving"], 1),
                   moving_after=tot["moving_after"],
                   raw_next_scan_not_better_share=raw_bad / max(mv_c, 1),
                   default_next_scan_not_better_share=def_bad / max(mvz_c, 1))
    print(f"all: {tot['moving']} moving points, {100 * summary['rejected_share']:.1f}% in groups the evidence "
          f"rejects; next-scan check, moving points in clusters not closer than with zero flow: raw "
          f"{100 * summary['raw_next_scan_not_better_share']:.1f}%, default (zeroed) "
          f"{100 * summary['default_next_scan_not_better_share']:.1f}%")
    return dict(frames=rows, summary=summary, out_dir=str(args.out_dir))


def launches(args) -> dict:
    """Ops and kernels of one problem_evidence call (a synthetic problem, solver order)."""
    from types import SimpleNamespace

    from torch.profiler import ProfilerActivity, profile

    from floxels_ext.estimator.group import problem_evidence

    cfg = FloxelsConfig(evidence="score")
    dev = torch.device(args.device)
    g = torch.Generator().manual_seed(0)
    n = args.points
    pts = torch.rand(n, 3, generator=g) * torch.tensor([60.0, 60.0, 4.0])
    lab = torch.randint(-1, 60, (n,), generator=g)  # ~1/60 unclustered
    cell = ((pts / cfg.voxel_size).floor().long() * torch.tensor([1, 1000, 1000000])).sum(1)
    order = torch.argsort(torch.where(lab >= 0, lab + (1 << 40), cell), stable=True)  # the solver's (cluster, cell)
    pts, lab, cell = pts[order], lab[order], cell[order]
    compact = torch.unique(cell, return_inverse=True)[1].to(torch.int32)
    dts, origins, offsets, weights = [], [], [], []
    for k, t in enumerate([-2.0, -1.0, 1.0, 2.0, 3.0, -3.0][:args.supports]):
        d = build_dt((pts + torch.tensor([0.3 * t, 0.0, 0.0])).to(dev), cfg)
        dts.append(d.values)
        origins.append(d.origin)
        offsets.append(t)
        weights.append(cfg.lambda_d * cfg.time_weight(int(t)))
    problem = SimpleNamespace(points=pts.to(dev), labels=lab.to(dev),
                              corners=SimpleNamespace(corner_idx=compact[:, None].expand(n, 8).to(dev)),
                              dts=dts, origins=origins, time_offsets=offsets, weights=weights)
    flow = (torch.randn(n, 3, generator=g) * 0.3).to(dev)
    problem_evidence(cfg, problem, flow)  # warm-up
    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if dev.type == "cuda" else [])
    with profile(activities=acts) as prof:
        problem_evidence(cfg, problem, flow)
        if dev.type == "cuda":
            torch.cuda.synchronize()
    ev = [e for e in prof.events() if e.device_type.name == "CPU" and e.name.startswith(("aten::", "floxels::"))]
    top = [e for e in ev if e.cpu_parent is None or not e.cpu_parent.name.startswith(("aten::", "floxels::"))]
    kernels = [e for e in prof.events()
               if e.device_type.name == "CUDA" and not e.name.startswith(("Memcpy", "Memset"))]
    counts: dict[str, int] = {}
    for e in top:
        counts[e.name] = counts.get(e.name, 0) + 1
    out = dict(points=n, supports=args.supports, top_level_ops=len(top), all_ops=len(ev),
               cuda_kernels=len(kernels) if dev.type == "cuda" else None, top_level=counts)
    print(f"problem_evidence, {n} points, {args.supports} support scans, {dev.type}: {len(top)} top-level ops, "
          f"{len(ev)} ops in all" + (f", {len(kernels)} CUDA kernels" if dev.type == "cuda" else ""))
    for name, c in sorted(counts.items(), key=lambda kv: -kv[1]):
        print(f"  {c:3d}  {name}")
    for e in kernels:
        print(f"  kernel {e.name[:100]}")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("mode", choices=("accuracy", "time", "real", "launches"))
    ap.add_argument("out_dir", nargs="?", help="real: the OUT_DIR of a floxels run --raw-flow")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--scenes", nargs="+", default=["urban", "crossing", "highway"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1])
    ap.add_argument("--frames", type=int, default=None, help="target frames per sequence (accuracy: 2; time: 48)")
    ap.add_argument("--lidar", choices=("small", "full"), default=None,
                    help="32 x 512 or 64 x 1024 simulated lidar (default: small on the CPU, full on CUDA)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--points", type=int, default=50000, help="launches: points of the problem")
    ap.add_argument("--supports", type=int, default=4, help="launches: support scans (1-6)")
    ap.add_argument("--json", default=None)
    ap.add_argument("--dump", default=None, help="accuracy: NPZ of every frame's raw flow, truth and group residuals")
    args = ap.parse_args(argv)
    args.lidar = args.lidar or ("full" if args.device.startswith("cuda") else "small")
    args.frames = args.frames or (2 if args.mode == "accuracy" else 48)
    if args.mode == "real" and not args.out_dir:
        ap.error("real needs the OUT_DIR of a floxels run --raw-flow")
    out = {"accuracy": accuracy, "time": timing, "real": real, "launches": launches}[args.mode](args)
    out.update(mode=args.mode, device=args.device, lidar=args.lidar, host=platform.node(), torch=torch.__version__,
               gpu=torch.cuda.get_device_name() if args.device.startswith("cuda") else None)
    write_results(out, args.json, f"bench_evidence_{args.mode}.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
