"""Where the ``accurate`` preset loses against ``paper`` (issue 47): a map over lidar beams,
sequence lengths (windows at the sequence ends included), scene types and object speeds on the
simulator, and the shared real scans (the AV2 pair with labels; the KITTI sweeps label-free).

    python bench/accurate_map.py [--device cpu|cuda] [--beams 32 64 128] [--lengths 5 11 40]
                                 [--scenes urban crossing highway parking] [--seeds 60 61 62]
                                 [--frames ends|all|0,5,-1] [--real av2 kitti | --no-sim]
                                 [--variant LABEL=PRESET[,FIELD=VALUE...]] [--today]
                                 [--pass origins|poses|none] [--repeat N] [--budget SECONDS]
                                 [--sim-workers N] [--cache DIR | --no-cache] [--json PATH] [--md PATH]

On an H100 the whole map (3 beams x 3 lengths x 4 scenes x 3 seeds, 3 frames each, the real
data, three rows) is a few minutes: ``--device cuda --sim-workers 12 --budget 480`` (the
simulation runs in worker processes first, cached; a case not started within the budget is left
out and the tables say so). A run writes its JSON and markdown after every case, so a run cut
short keeps what it did; a second run with the same cache computes only what is missing.
On a host of N GPUs: N processes ``--shard K/N`` (``CUDA_VISIBLE_DEVICES=K``) on one ``--cache``,
then one ``--cached-only`` run that writes the tables of every case they finished
(``tools/gpu_map_shards.sh``).

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
(``paper`` is pinned by tests), with the time per frame of the run that computed them (on CUDA
synchronised, after one warm-up per row; ``--repeat N``: the median of N runs). ``--today``
adds the row ``accurate_today``: the preset as it was before issue 47's changes (TODAY below).
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
from _map_data import SCENES, av2_case, kitti_case, label_free_metrics, sim_case  # noqa: E402
from _map_report import group_rows, speed_table, table  # noqa: E402
from compare_rows import clean  # noqa: E402

from floxels_ext import FloxelsConfig, estimate_sequence  # noqa: E402

PKG = HERE.parent / "python" / "floxels_ext"
# the accurate preset before issue 47 (the row --today adds): the fields issue 47 changed, back
TODAY = ("accurate_today=accurate,reg_scale=support,max_offset=0,evidence_seen_mean=false,"
         "evidence_keep_unseen=false,refine_level=false,refine_spread=0,evidence_upright=false")
HELD_OUT = [60, 61, 62]  # seeds no setting of the accurate preset was chosen on (tuning: 0 1 2)


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

    def cached(self, case, label, cfg) -> bool:
        """Whether every scored frame of (case, variant) is in the cache."""
        return self.cache is not None and all(
            (self.cache / f"{self.key(case, label, cfg, f)}.npz").exists() for f in case.frames)

    def flows(self, case, label, cfg) -> tuple[dict, float | None]:
        """({frame: flow}, seconds per frame or None: the mean over the frames that have one)."""
        out, todo, secs = {}, [], []
        for f in case.frames:
            p = self.cache / f"{self.key(case, label, cfg, f)}.npz" if self.cache else None
            if p is not None and p.exists():
                z = np.load(p)
                out[f] = z["flow"]
                if "seconds" in z.files and np.isfinite(z["seconds"]):
                    secs.append(float(z["seconds"]))
            else:
                todo.append(f)
        if not todo:
            return out, float(np.mean(secs)) if secs else None
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
        per_frame = float(np.median(runs)) / len(todo)
        for f, flow in got.items():
            out[f] = flow
            if self.cache:
                self.cache.mkdir(parents=True, exist_ok=True)
                np.savez(self.cache / f"{self.key(case, label, cfg, f)}.npz", flow=flow, seconds=per_frame)
        secs += [per_frame] * len(todo)
        return out, float(np.mean(secs))


def parse_args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--beams", nargs="+", type=int, default=[32, 64, 128])
    ap.add_argument("--lengths", nargs="+", type=int, default=[5, 11, 40])
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
    ap.add_argument("--seeds", nargs="+", type=int, default=HELD_OUT, help="simulator seeds, each for every scene "
                    "(default: the held-out 60 61 62; the preset was tuned on 0 1 2)")
    ap.add_argument("--frames", default="ends", help="scored frames: ends (first, middle, last), all, or 0,5,-1")
    ap.add_argument("--azimuth", type=int, default=2048, help="simulated lidar azimuth steps")
    ap.add_argument("--max-range", type=float, default=50.0)
    ap.add_argument("--no-sim", action="store_true", help="only the real data (--real)")
    ap.add_argument("--real", nargs="*", default=[], choices=("av2", "kitti"))
    ap.add_argument("--kitti-frames", default="ends")
    ap.add_argument("--variant", action="append", default=[], metavar="LABEL=PRESET[,FIELD=VALUE...]",
                    help="rows besides paper (default: accurate=accurate)")
    ap.add_argument("--today", action="store_true", help=f"also the row {TODAY.split('=')[0]} (the accurate "
                    "preset before issue 47), after the --variant rows")
    ap.add_argument("--pass", dest="pass_", choices=("origins", "poses", "none"), default="origins",
                    help="what the API gets besides the scans: sensor_origins=, poses= or nothing")
    ap.add_argument("--iters", type=int, default=None, help="max_iters of every row (smoke runs only)")
    ap.add_argument("--repeat", type=int, default=1, help="timed runs per computed case (median)")
    ap.add_argument("--budget", type=float, default=0.0, help="seconds: no case is started after this (0: none); "
                    "the seeds are the outer loop, so a cut run has every cell of its first seeds")
    ap.add_argument("--sim-workers", type=int, default=0, help="simulate the cases in this many processes first "
                    "(0: each when it is reached)")
    ap.add_argument("--shard", default=None, metavar="K/N", help="only the cases K, K+N, K+2N, ... (0 <= K < N) of the "
                    "listed ones: N processes (one a GPU) share one --cache; then one run with --cached-only reports all")
    ap.add_argument("--cached-only", action="store_true", help="report only the cases whose every row is in the "
                    "cache (the others listed as left out); estimates nothing")
    ap.add_argument("--cache", default=str(HERE / "results" / "accurate_map_cache"))
    ap.add_argument("--no-cache", action="store_true")
    ap.add_argument("--code-tag", default=None, help="cache key of the code of rows other than paper (default: a "
                    "hash of the estimator's and ops' sources)")
    ap.add_argument("--json", default=str(HERE / "results" / "accurate_map.json"))
    ap.add_argument("--md", default=None, help="the markdown tables (default: the --json path with .md)")
    args = ap.parse_args(argv)
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        ap.error("--device cuda requested but no CUDA device is available")
    if args.repeat < 1:
        ap.error("--repeat must be >= 1")
    if args.budget < 0 or args.sim_workers < 0:
        ap.error("--budget and --sim-workers must be >= 0")
    args.md = args.md or str(Path(args.json).with_suffix(".md"))
    args.shard_k, args.shard_n = 0, 1
    if args.shard is not None:
        try:
            k, n = (int(x) for x in args.shard.split("/"))
        except ValueError:
            ap.error(f"--shard {args.shard}: expected K/N, e.g. 0/4")
        if not 0 <= k < n:
            ap.error(f"--shard {args.shard}: K must be in 0..N-1")
        args.shard_k, args.shard_n = k, n
    if args.cached_only and args.no_cache:
        ap.error("--cached-only contradicts --no-cache")
    return args


def _simulate(spec):
    """Worker: one simulated case into the cache (its sequence only)."""
    sc, sd, b, n, frames, max_range, azimuth, cache = spec
    sim_case(sc, sd, b, n, frames, max_range, azimuth, cache)
    return f"sim/b{b}/L{n}/{sc}/s{sd}"


def presimulate(specs, args) -> None:
    """Every simulated sequence into the cache, ``--sim-workers`` at a time (the CPU's share of a
    map on CUDA: at 128 beams ~0.3 s a frame on one core)."""
    from concurrent.futures import ProcessPoolExecutor

    cache = Path(args.cache) / "sim"
    t0 = time.perf_counter()
    jobs = [(sc, sd, b, n, args.frames, args.max_range, args.azimuth, cache) for sc, sd, b, n in specs]
    with ProcessPoolExecutor(args.sim_workers) as pool:
        for k, key in enumerate(pool.map(_simulate, jobs), 1):
            if k % 12 == 0 or k == len(jobs):
                print(f"  simulated {k}/{len(jobs)} ({key}) [{time.perf_counter() - t0:.0f} s]", flush=True)


def write_report(args, argv, runner, variants, records, skipped, t_all, final: bool) -> None:
    """The JSON and the markdown tables of the cases done so far (after every case)."""
    labels = [lab for lab, _ in variants]
    rows = group_rows(records, labels)
    dev = torch.cuda.get_device_name() if args.device.startswith("cuda") else args.device
    cmd = "python bench/accurate_map.py " + " ".join(sys.argv[1:] if argv is None else argv)
    head = (f"## accurate map ({dev}, seeds {args.seeds}, --pass {args.pass_}, {len(records)} cases"
            + (f", {len(skipped)} left out by --budget" if skipped else "") + ("" if final else ", in progress") + ")")
    md = (f"{head}\n\n`{cmd}`\n\n{table(rows, labels)}\n\nDynamic EPE by true speed, all simulated frames:\n\n"
          f"{speed_table(rows, labels)}\n")
    if skipped:
        md += "\nLeft out by --budget: " + ", ".join(skipped) + "\n"
    out = {"command": cmd, "device": args.device, "gpu": dev if args.device.startswith("cuda") else None,
           "host": platform.node(), "threads": torch.get_num_threads(), "code": runner.code, "final": final,
           "variants": {lab: dataclasses.asdict(cfg) for lab, cfg in variants},
           "rows": [{"group": g, "cell": name, "metrics": row} for g, name, row in rows],
           "cases": [{k: r[k] for k in ("key", "attrs", "frames", "positions", "seconds")} for r in records],
           "skipped": skipped, "total_seconds": time.perf_counter() - t_all}
    for path, text in ((args.json, json.dumps(clean(out), indent=1, default=str)), (args.md, md)):
        os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
        tmp = path + ".tmp"
        with open(tmp, "w") as fh:
            fh.write(text)
        os.replace(tmp, path)
    if final:
        print("\n" + md)


def main(argv=None) -> int:
    args = parse_args(argv)
    specs_v = (args.variant or ["accurate=accurate"]) + ([TODAY] if args.today else [])
    variants = [("paper", FloxelsConfig())] + [parse_variant(v) for v in specs_v]
    if args.iters:
        variants = [(lab, cfg.replace(max_iters=args.iters)) for lab, cfg in variants]
    runner = Runner(args)
    t_all = time.perf_counter()
    # seeds outermost: a run cut by --budget has every cell of its first seeds
    specs = [] if args.no_sim else [(sc, sd, b, n) for sd in args.seeds for b in args.beams for n in args.lengths
                                    for sc in args.scenes]
    cases = [("sim", s) for s in specs] + [(r, None) for r in ("av2", "kitti") if r in args.real]
    cases = cases[args.shard_k::args.shard_n]
    specs = [s for k, s in cases if k == "sim"]
    if args.sim_workers and specs and not args.no_cache and not args.cached_only:
        presimulate(specs, args)
    records, skipped = [], []
    for i, (kind, spec) in enumerate(cases, 1):
        if args.budget and time.perf_counter() - t_all > args.budget:
            skipped += ["/".join(map(str, s)) if s else k for k, s in cases[i - 1:]]
            print(f"  --budget {args.budget:g} s spent: {len(skipped)} case(s) left out", flush=True)
            break
        if kind == "sim":
            sc, sd, b, n = spec
            case = sim_case(sc, sd, b, n, args.frames, args.max_range, args.azimuth,
                            None if args.no_cache else Path(args.cache) / "sim")
        else:
            case = av2_case() if kind == "av2" else kitti_case(args.kitti_frames)
        if args.cached_only and not all(runner.cached(case, lab, cfg) for lab, cfg in variants):
            skipped.append(case.key + " (not cached)")
            continue
        rec = {"key": case.key, "attrs": case.attrs, "frames": case.frames, "positions": case.positions,
               "truth": case.truth and {f: case.truth[f] for f in case.frames}, "preds": {}, "seconds": {},
               "label_free": {}}
        for lab, cfg in variants:
            preds, secs = runner.flows(case, lab, cfg)
            rec["preds"][lab], rec["seconds"][lab] = preds, secs
            if case.truth is None:
                rec["label_free"][lab] = label_free_metrics(case, preds)
        records.append(rec)
        times = " ".join(f"{lab} {s:.3f}" for lab, s in rec["seconds"].items() if s is not None)
        print(f"  [{i}/{len(cases)}] {case.key}: frames {case.frames}, s/frame {times or 'cached'} "
              f"[{time.perf_counter() - t_all:.0f} s]", flush=True)
        write_report(args, argv, runner, variants, records, skipped, t_all, final=False)
    write_report(args, argv, runner, variants, records, skipped, t_all, final=True)
    print(f"wrote {args.json} and {args.md} [{time.perf_counter() - t_all:.0f} s]")
    return 0


if __name__ == "__main__":
    sys.exit(main())
