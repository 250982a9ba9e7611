"""Where does a preset's time go, part by part (issue 47's speed item: `accurate` against `paper`)?

Times ``estimate_sequence`` on simulated sequences (bench/_map_data.py's cases: scans in one world
frame, the sensor positions and, where the preset's ``visibility`` reads it, the removed ground,
as bench/accurate_map.py passes them) and splits each call into its parts by wrapping the
estimator's functions: the distance transforms and the sights built with them, DBSCAN and the
sorting, the optimiser, and, after it, each step of ``estimator/post.py`` (the sights' bits, the
evidence test and its judgement on what was seen, the rigid refinement with its Levenberg-Marquardt
solves, velocity search and residual look-ups, the spreading), the read-back. Parts nest (a
child's time is inside its parent's); ``self`` is a part's time less its children's.

Per part: seconds per frame, calls, ATen/floxels ops launched (top-level calls: on CUDA about one
kernel launch each) and host synchronisations (``aten::nonzero``, ``aten::_local_scalar_dense``
and estimator/host_reads.py's merged reads), counted in one extra run under ``torch.profiler``
(CPU activity only); on CUDA also every synchronisation ``torch.cuda.set_sync_debug_mode``
reports (e.g. ``torch.tensor(..., device="cuda")``, blocking copies), by part. ``--sync``: on CUDA each part waits for the device before and after, so
its time includes its GPU work (the run then loses its overlaps; compare parts, not totals).

    PYTHONPATH=python python tools/preset_parts.py [--device cpu|cuda] [--beams 32] [--lengths 11]
        [--scene urban] [--seed 60] [--frames ends] [--iters 50] [--repeat 3]
        [--variant LABEL=PRESET[,FIELD=VALUE...]] [--sync] [--json PATH]

Default rows: ``paper`` and ``accurate``; ``--variant`` adds rows (e.g. ``no_level=accurate,
refine_level=false`` for what one field costs).
"""

from __future__ import annotations

import argparse
import inspect
import json
import sys
import time
import warnings
from collections import defaultdict
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from _map_data import sim_case  # noqa: E402
from accurate_map import parse_variant, sensor_kwargs  # noqa: E402

from floxels_ext import FloxelsConfig, estimate_sequence  # noqa: E402
from floxels_ext.estimator import distance, evidence, group, post, refine, spread  # noqa: E402

try:
    from floxels_ext.estimator import host_reads  # noqa: E402
except ImportError:  # (a checkout before the merged reads)
    host_reads = None
from floxels_ext.ops import solver as solver_ops  # noqa: E402

# (part, parent part or None, object, attribute): each wrapped where its caller looks it up (an
# attribute the checkout lacks is skipped: the tool also measures the code before issue 47's
# speed work, where post.py called rigid_refine / spread_rigid one problem at a time)
PARTS = [
    ("dt+sight", None, group, "build_dt"),
    ("dt+sight", None, distance, "build_dt"),  # EarlyDts (single frames)
    ("sight", "dt+sight", distance, "scan_sight"),
    ("dbscan+setup", None, group, "_targets"),
    ("optimiser", None, solver_ops.PackedProblems, "run"),
    ("post", None, group, "after_optimisation_all"),
    ("post", None, group, "after_optimisation"),  # (before the host reads were merged)
    ("observed_bits", "post", post, "observed_bits"),
    ("evidence", "post", post, "run_evidence"),
    ("seen_evidence", "evidence", evidence, "seen_evidence"),
    ("sensor_velocity", "post", post, "sensor_velocity"),
    ("rigid_refine", "post", post, "rigid_refine_steps"),
    ("rigid_refine", "post", post, "rigid_refine"),
    ("cluster_means", "rigid_refine", refine, "cluster_means"),
    ("subsample", "rigid_refine", refine, "_subsample"),
    ("rigid_lm", "rigid_refine", refine._LevenbergMarquardt, "solve"),
    ("search", "rigid_refine", refine, "_search"),
    ("residuals", "rigid_refine", refine, "_weighted_residual"),
    ("spread", "post", post, "spread_rigid_steps"),
    ("spread", "post", post, "spread_rigid"),
    ("spread_residuals", "spread", spread, "_weighted_residual"),
    ("restore", None, group, "restore_outputs"),
]
PARENT = {name: parent for name, parent, _, _ in PARTS}  # each part once, in order
SYNC_OPS = ("aten::nonzero", "aten::_local_scalar_dense", "host_read")  # host_read: host_reads._read's transfer
VIEWS = {"aten::" + n for n in ("unsqueeze", "squeeze", "select", "slice", "view", "reshape", "expand",
                                  "expand_as", "transpose", "unbind", "detach", "as_strided", "alias", "t",
                                  "permute", "diagonal", "empty", "empty_like", "lift_fresh", "_unsafe_view",
                                  "movedim", "split", "chunk", "narrow", "resolve_conj", "resolve_neg")}


class Parts:
    """The wrappers: per part its time (seconds), calls, and, while ``counting``, its host
    synchronisations seen by ``torch.cuda.set_sync_debug_mode``."""

    def __init__(self, sync: bool, cuda: bool) -> None:
        self.sync, self.cuda = sync and cuda, cuda
        self.time = defaultdict(float)
        self.calls = defaultdict(int)
        self.stack: list[str] = []
        self.saved = []

    def install(self) -> None:
        read = getattr(host_reads, "_read", None) if host_reads is not None else None  # the merged reads (a .tolist(): no ATen op of its own)
        if read is not None:
            def counted(counts):
                with torch.profiler.record_function("host_read"):
                    return read(counts)
            self.saved.append((host_reads, "_read", read))
            host_reads._read = counted
        for name, _, obj, attr in PARTS:
            fn = getattr(obj, attr, None)
            if fn is None:
                continue
            self.saved.append((obj, attr, fn))
            setattr(obj, attr, self._wrap(name, fn))

    def remove(self) -> None:
        for obj, attr, fn in reversed(self.saved):
            setattr(obj, attr, fn)
        self.saved.clear()

    def _wrap(self, name, fn):
        parts = self

        def wrapped(*a, **k):
            parts.calls[name] += 1
            out = parts._timed(name, fn, a, k)
            return parts._steps(name, out) if inspect.isgenerator(out) else out
        return wrapped

    def _timed(self, name, fn, a, k):
        if self.sync:
            torch.cuda.synchronize()
        self.stack.append(name)
        t0 = time.perf_counter()
        try:
            with torch.profiler.record_function("part:" + name):
                return fn(*a, **k)
        finally:
            if self.sync:
                torch.cuda.synchronize()
            self.time[name] += time.perf_counter() - t0
            self.stack.pop()

    def _steps(self, name, gen):
        """A generator part (estimator/host_reads.py's steps): each resumption timed."""
        value = None
        while True:
            try:
                want = self._timed(name, gen.send, (value,), {})
            except StopIteration as stop:
                return stop.value
            value = yield want

    def reset(self) -> None:
        self.time.clear()
        self.calls.clear()


def count_ops(fn) -> tuple[dict, dict]:
    """(ops launched, host synchronisations) per part (inclusive, like the times; ``-``: outside
    every part, ``*``: all) of one call of ``fn`` under torch.profiler (CPU activity)."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU]) as prof:
        fn()
    ops, syncs = defaultdict(int), defaultdict(int)
    for e in prof.events():
        within, p = set(), e.cpu_parent  # every part the event is inside (parts nest)
        while p is not None:
            if p.name.startswith("part:"):
                within.add(p.name[5:])
            p = p.cpu_parent
        parent = e.cpu_parent
        top = parent is None or not parent.name.startswith(("aten::", "floxels::"))
        launch = top and e.name.startswith(("aten::", "floxels::")) and e.name not in VIEWS and (
            e.name != "aten::to" or any(c.name == "aten::_to_copy" for c in e.cpu_children))
        for part in within or {"-"}:
            ops[part] += launch
            syncs[part] += e.name in SYNC_OPS
        ops["*"] += launch
        syncs["*"] += e.name in SYNC_OPS
    return ops, syncs


def measure(case, label, cfg, args, parts: Parts) -> dict:
    kw = sensor_kwargs(case, cfg, "origins")
    frames = case.frames
    cuda = args.device.startswith("cuda")

    def call():
        estimate_sequence(case.scans, cfg, device=args.device, frames=frames, **kw)
        if cuda:
            torch.cuda.synchronize()

    call()  # warm-up (and, on CUDA, every path initialised)
    walls, per_part = [], []
    for _ in range(args.repeat):
        parts.reset()
        t0 = time.perf_counter()
        call()
        walls.append(time.perf_counter() - t0)
        per_part.append(dict(parts.time))
    best = min(range(args.repeat), key=lambda r: walls[r])
    calls = dict(parts.calls)
    ops, syncs = count_ops(call)
    cuda_syncs = defaultdict(int)
    if cuda:  # every synchronisation CUDA's sync debug mode reports, by the part it happens in
        def seen(message, *a, **k):
            if "synchroniz" in str(message).lower():
                cuda_syncs[parts.stack[-1] if parts.stack else "-"] += 1
        with warnings.catch_warnings():
            warnings.simplefilter("always")
            warnings.showwarning = seen
            torch.cuda.set_sync_debug_mode("warn")
            try:
                call()
            finally:
                torch.cuda.set_sync_debug_mode(0)
    n = len(frames)
    rows = {}
    for name, parent in PARENT.items():
        if name not in per_part[best] and name not in ops:
            continue
        t = per_part[best].get(name, 0.0)
        kids = sum(per_part[best].get(c, 0.0) for c, p in PARENT.items() if p == name)
        rows[name] = {"parent": parent, "s_per_frame": t / n, "self_s_per_frame": (t - kids) / n,
                      "calls_per_frame": calls.get(name, 0) / n, "ops_per_frame": ops.get(name, 0) / n,
                      "syncs_per_frame": syncs.get(name, 0) / n, "cuda_syncs_per_frame": cuda_syncs.get(name, 0) / n}
    rows["(other)"] = {"parent": None, "s_per_frame": (walls[best] - sum(per_part[best].get(p, 0.0)
                                                                          for p, q in PARENT.items() if q is None)) / n,
                       "ops_per_frame": ops.get("-", 0) / n, "syncs_per_frame": syncs.get("-", 0) / n}
    return {"label": label, "case": case.key, "frames": frames, "wall_s_per_frame": walls[best] / n,
            "wall_runs": walls, "ops_per_frame": ops["*"] / n, "syncs_per_frame": syncs["*"] / n,
            "cuda_syncs_per_frame": sum(cuda_syncs.values()) / n if cuda else None, "parts": rows}


def print_rows(results: list[dict]) -> None:
    labels = [r["label"] for r in results]
    names = [k for k in [*PARENT, "(other)"] if any(k in r["parts"] for r in results)]
    depth = {}
    for name, parent in PARENT.items():
        depth[name] = 0 if parent is None else depth[parent] + 1
    head = f"{'part':<24}" + "".join(f" | {lab[:10]:>10} ms  ops  syn" for lab in labels)
    print(head)
    print("-" * len(head))
    for name in names:
        line = f"{'  ' * depth.get(name, 0) + name:<24}"
        for r in results:
            p = r["parts"].get(name)
            line += (" | " + " " * 27) if p is None else (
                f" | {1e3 * p['s_per_frame']:13.1f} {p['ops_per_frame']:5.0f} {p['syncs_per_frame']:4.0f}")
        print(line)
    line = f"{'wall (per frame)':<24}"
    for r in results:
        line += f" | {1e3 * r['wall_s_per_frame']:13.1f} {r['ops_per_frame']:5.0f} {r['syncs_per_frame']:4.0f}"
    print(line)
    if results and results[0]["cuda_syncs_per_frame"] is not None:
        print("CUDA synchronisations per frame (sync debug mode): "
              + ", ".join(f"{r['label']} {r['cuda_syncs_per_frame']:.1f}" for r in results))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--beams", nargs="+", type=int, default=[32])
    ap.add_argument("--lengths", nargs="+", type=int, default=[11])
    ap.add_argument("--scene", default="urban")
    ap.add_argument("--seed", type=int, default=60)
    ap.add_argument("--frames", default="ends", help="scored frames: ends, all, or a comma list")
    ap.add_argument("--azimuth", type=int, default=2048)
    ap.add_argument("--iters", type=int, default=50, help="max_iters of every row (0: the preset's)")
    ap.add_argument("--repeat", type=int, default=3, help="timed runs (the fastest is reported)")
    ap.add_argument("--variant", action="append", default=[], metavar="LABEL=PRESET[,FIELD=VALUE...]")
    ap.add_argument("--sync", action="store_true", help="CUDA: synchronise around every part")
    ap.add_argument("--sim-cache", default=str(ROOT / "bench" / "results" / "accurate_map_cache" / "sim"))
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    variants = [("paper", FloxelsConfig()), ("accurate", FloxelsConfig.preset("accurate"))]
    variants += [parse_variant(v) for v in args.variant]
    if args.iters:
        variants = [(lab, cfg.replace(max_iters=args.iters)) for lab, cfg in variants]
    parts = Parts(args.sync, args.device.startswith("cuda"))
    parts.install()
    out = []
    try:
        for beams in args.beams:
            for length in args.lengths:
                case = sim_case(args.scene, args.seed, beams, length, args.frames, azimuth=args.azimuth,
                                cache=Path(args.sim_cache))
                print(f"\n## {case.key}, frames {case.frames}, {args.device}, max_iters {args.iters or 'preset'}")
                res = [measure(case, lab, cfg, args, parts) for lab, cfg in variants]
                print_rows(res)
                out += res
    finally:
        parts.remove()
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({"argv": sys.argv[1:], "device": args.device, "rows": out}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
