"""``floxels run`` end to end vs the optimiser's ceiling (issue 16).

Builds one simulated sequence (``--beams`` lidar, ``--frames`` frames, ground included) and writes
it twice: KITTI style (``velodyne/NNNNNN.bin`` + ``poses.txt``) and as an Argoverse 2 log
(``sensors/lidar/<ns>.feather`` + ``city_SE3_egovehicle.feather``). Then, in one process:

* ``floxels run`` on each (after a short warm-up run: CUDA context, kernels), frames/s end to end
  and the per-stage breakdown the run records in ``run_summary.json``;
* the ceiling: ``estimate_sequence`` on the same preprocessed, ego-motion-compensated scans,
  already in memory (one call, all frames), timed once in every repetition, after its runs
  (``--repeat``: each run's ratio to the ceiling of its repetition; the table shows the median);
* the serial host work per frame (read + preprocessing, the compiled CPU op, on one thread) for reference.

    python bench/bench_run.py                             # GPU host: 64 frames, 128 beams
    python bench/bench_run.py --frames 16 --beams 32      # CPU-sized
    python bench/bench_run.py --repeat 3 --variant "w4=--writers 4"   # medians of 3, a variant
    python bench/bench_run.py --repeat 3 --variant "two-kernel=FLOXELS_SOLVER_PERSISTENT=0"   # an environment variant
    python bench/bench_run.py --repeat 3 --frames 768 --variant "e1=--engines 1" --variant "e2=--engines 2"

The default rows run with ``floxels run``'s default engines (2 on CUDA, 1 on the CPU). With
several engines the stage columns are per engine (the summary sums them over the engines) and
the workers column ends in xN; a run only shows the second engine's effect once it outlasts its
start (~2-4 s: process, CUDA context, warm-up; the first run of a process also starts the fork
server), hence the longer sequence in the example.

Prints a table and writes bench/results/bench_run_<device>.json.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from floxels_ext import cli
from floxels_ext.lidar.preprocess import Preprocess, preprocess_mask, transform_points


def _is_env(word: str) -> bool:
    """A --variant word that sets an environment variable (NAME=VALUE, NAME upper case)."""
    return re.fullmatch(r"[A-Z][A-Z0-9_]*=.*", word) is not None


def build(root: Path, frames: int, beams: int, azimuth: int, seed: int) -> tuple[Path, Path, int]:
    import pyarrow as pa
    import pyarrow.feather as feather

    from floxels_ext.evaluation.sim import simulate_sequence

    seq = simulate_sequence("urban", frames, seed, beams=beams, azimuth_steps=azimuth)
    kitti, av2 = root / "kitti", root / "av2"
    (kitti / "velodyne").mkdir(parents=True)
    (av2 / "sensors" / "lidar").mkdir(parents=True)
    rows = {k: [] for k in ("timestamp_ns", "qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m")}
    npts = []
    for i, fr in enumerate(seq.frames):
        p = transform_points(fr.points, np.linalg.inv(fr.pose))
        npts.append(len(p))
        inten = np.zeros(len(p), np.float32)
        np.c_[p, inten].astype(np.float32).tofile(kitti / "velodyne" / f"{i:06d}.bin")
        t = 1_600_000_000_000_000_000 + 100_000_000 * i
        feather.write_feather(pa.table({"x": p[:, 0], "y": p[:, 1], "z": p[:, 2], "intensity": inten}),
                              str(av2 / "sensors" / "lidar" / f"{t}.feather"), compression="uncompressed")
        R = fr.pose[:3, :3]
        yaw = np.arctan2(R[1, 0], R[0, 0])  # the simulated ego only yaws
        for k, v in zip(rows, (t, np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2), *fr.pose[:3, 3])):
            rows[k].append(v)
    np.savetxt(kitti / "poses.txt", np.stack([f.pose[:3] for f in seq.frames]).reshape(-1, 12), fmt="%.9g")
    feather.write_feather(pa.table(rows), str(av2 / "city_SE3_egovehicle.feather"))
    return kitti, av2, int(np.mean(npts))


NAN = float("nan")


def built(args, tmp: Path) -> tuple[Path, Path, int, str]:
    """(kitti, av2, raw points a frame, how): the simulated files, built in ``tmp`` or, with
    ``--data``, reused from there when its ``meta.json`` names the same sequence."""
    meta = {"frames": args.frames, "beams": args.beams, "azimuth": args.azimuth, "seed": args.seed}
    root = args.data or tmp
    mfile = root / "meta.json"
    if args.data is not None and mfile.is_file():
        old = json.loads(mfile.read_text())
        if {k: old.get(k) for k in meta} == meta:
            return root / "kitti", root / "av2", old["points"], f"reused from {root}"
        sys.exit(f"bench_run.py: --data {root} holds another sequence ({old}); give an empty folder")
    if args.data is not None and root.exists() and any(root.iterdir()):
        sys.exit(f"bench_run.py: --data {root} is not empty and has no meta.json")
    root.mkdir(parents=True, exist_ok=True)
    kitti, av2, npts = build(root, args.frames, args.beams, args.azimuth, args.seed)
    if args.data is not None:
        mfile.write_text(json.dumps(dict(meta, points=npts)) + "\n")
    return kitti, av2, npts, "built"


def run_cli(args_list: list[str]) -> tuple[float, dict]:
    t0 = time.perf_counter()
    rc = cli.main(args_list)
    wall = time.perf_counter() - t0
    if rc != 0:
        sys.exit(f"floxels run failed (exit {rc}): {' '.join(args_list)}")
    out = Path(args_list[args_list.index("--out") + 1])
    return wall, json.loads((out / "run_summary.json").read_text())


def prepared_scans(kitti: Path) -> tuple[list, float, float]:
    """The KITTI sequence's scans read, preprocessed (the CPU op) and moved into one world frame
    on this thread, as ``floxels run`` hands them to the method (the same origin: the first
    pose's position on the pipeline's anchor grid, so the same voxel and DT grids and the same
    work); and the serial read and preprocessing seconds."""
    from floxels_ext.lidar.io import read_points, read_poses
    from floxels_ext.lidar.dataset.layout import snap_anchor

    files = sorted((kitti / "velodyne").glob("*.bin"))
    poses = read_poses(kitti / "poses.txt")
    settings = Preprocess()
    t_read = t_pre = 0.0
    scans = []
    anchor = snap_anchor(poses[0][:3, 3])
    for f, T in zip(files, poses):
        t0 = time.perf_counter()
        pts = read_points(f).points
        t1 = time.perf_counter()
        m = preprocess_mask(pts, settings)
        t2 = time.perf_counter()
        t_read, t_pre = t_read + t1 - t0, t_pre + t2 - t1
        T = T.copy()
        T[:3, 3] -= anchor
        scans.append(transform_points(pts[m], T))
    return scans, t_read, t_pre


class Ceiling:
    """``estimate_sequence`` on the prepared scans (warmed up at construction); ``time()`` is
    one call's seconds, ``summary()`` the median of the calls so far."""

    def __init__(self, kitti: Path, scans_n: int, device: str, options: dict) -> None:
        from floxels_ext.estimator.config import FloxelsConfig
        from floxels_ext.estimator.api import estimate_sequence

        self.scans, self.t_read, self.t_pre = prepared_scans(kitti)
        # the same work as floxels run's default: the motion evidence with unexplained flow zeroed
        self.cfg = FloxelsConfig(**{"num_scans": scans_n, "evidence": "zero", **options})
        self.device, self.estimate, self.times = device, estimate_sequence, []
        estimate_sequence(self.scans[:8], self.cfg, device=device, frames=[3])  # warm-up
        self._sync()

    def _sync(self) -> None:
        if self.device.startswith("cuda"):
            torch.cuda.synchronize()

    def time(self) -> float:
        t0 = time.perf_counter()
        self.estimate(self.scans, self.cfg, device=self.device)
        self._sync()
        self.times.append(time.perf_counter() - t0)
        return self.times[-1]

    def summary(self) -> dict:
        est, n = statistics.median(self.times), len(self.scans)
        return {"frames": n, "estimate_s": est, "frames_per_s": n / est,
                "repeats_frames_per_s": [n / t for t in self.times], "serial_read_ms": 1e3 * self.t_read / n,
                "serial_preprocess_ms": 1e3 * self.t_pre / n,
                "kept_points_mean": int(np.mean([len(s) for s in self.scans]))}


def ceiling(kitti: Path, scans_n: int, device: str, options: dict, repeat: int = 1) -> dict:
    """Serial host work per frame, then estimate_sequence on the prepared scans (one call; the
    median of ``repeat`` calls)."""
    c = Ceiling(kitti, scans_n, device, options)
    for _ in range(repeat):
        c.time()
    return c.summary()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=64)
    ap.add_argument("--beams", type=int, default=128)
    ap.add_argument("--azimuth", type=int, default=1800, help="azimuth steps per revolution (default 1800)")
    ap.add_argument("--scans", type=int, default=None,
                    help="scans per window of every run (default: each run's preset's own, as a user gets it); the "
                         "ceiling uses this or the paper's 5")
    ap.add_argument("--device", default=None, help="cuda or cpu (default: cuda if there is a GPU)")
    ap.add_argument("--max-iters", type=int, help="optimiser iterations (default: the config's)")
    ap.add_argument("--run-args", default="", help="extra floxels run arguments (quoted)")
    ap.add_argument("--variant", action="append", default=[], metavar="LABEL=ARGS",
                    help="also time floxels run with these extra arguments (repeatable), e.g. "
                         "'gpu-pre=--preprocess-device cuda'; rows are compared in the same run. A NAME=VALUE "
                         "word (upper case, e.g. FLOXELS_SOLVER_PERSISTENT=0) is set in the environment for that "
                         "variant's runs instead")
    ap.add_argument("--repeat", type=int, default=1, metavar="R",
                    help="time every run (and the ceiling) R times, interleaved; the table shows the median "
                         "run of each (hosts vary by ~10%% from run to run)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--gil-switch-interval", type=float, default=None, metavar="S",
                    help="floxels_ext.lidar.dataset.stream.GIL_SWITCH_INTERVAL for the runs "
                         "(0 = Python's default, "
                         "to compare with the pipeline's setting)")
    ap.add_argument("--data", type=Path, help="keep the simulated files in this folder and reuse them when it "
                    "holds the same --frames/--beams/--azimuth/--seed (tools/ab_bench.py: one build of ~1 min, not one "
                    "a bench run)")
    ap.add_argument("--no-ceiling", action="store_true", help="leave out the in-memory ceiling (paper preset)")
    ap.add_argument("--json", help="output (default bench/results/bench_run_<device>.json)")
    ap.add_argument("--windows", type=Path, help="also write each timed run's [t0, t1] (time.time()) as a JSON "
                    "list of {name, t0, t1}, and for runs on several engines their steady part (from the last "
                    "engine's first frame to the last frame, NAME steady): tools/host_sampler.py --windows "
                    "summarises the GPU's busy share per window")
    args = ap.parse_args()
    if args.device is None:
        # asked through NVML, not by initialising CUDA in this process: the runs below are in this
        # process, and floxels run's --mps must come before this process's CUDA initialisation
        os.environ.setdefault("PYTORCH_NVML_BASED_CUDA_CHECK", "1")
        args.device = "cuda" if torch.cuda.is_available() else "cpu"

    if args.gil_switch_interval is not None:
        import floxels_ext.lidar.dataset.stream as engine

        engine.GIL_SWITCH_INTERVAL = args.gil_switch_interval or None
    tmp = Path(tempfile.mkdtemp(prefix="bench_run_"))
    try:
        t0 = time.perf_counter()
        kitti, av2, npts, how = built(args, tmp)
        print(f"sequence: {args.frames} frames, {args.beams} beams, {npts} raw points/frame (ground included), "
              f"{how} in {time.perf_counter() - t0:.1f} s", flush=True)
        options = {} if args.max_iters is None else {"max_iters": args.max_iters}
        # --scans only when asked (each --preset then brings its own window: accurate 11, as for a user);
        # the paper preset unless --run-args / a variant says otherwise (the later --preset wins):
        # floxels run's default is accurate since issue 42, and the ceiling below is the paper's
        common = ["--device", args.device, *(["--scans", str(args.scans)] if args.scans else []), "--preset", "paper",
                  *args.run_args.split()]
        if args.max_iters is not None:
            common += ["--max-iters", str(args.max_iters)]
        # warm-up: CUDA context, kernel loading, first allocations (not a user-visible cost per frame)
        run_cli(["run", str(kitti / "velodyne"), "--out", str(tmp / "warm"), "--poses", str(kitti / "poses.txt"),
                 "--frames", "0:6", "--force", *common])
        rows = {}
        variants = [("", [])] + [(v.partition("=")[0], v.partition("=")[2].split()) for v in args.variant]
        reps: dict[str, list] = {}
        windows: list[dict] = []
        # the paper preset's ceiling
        ceil_runs = None if args.no_ceiling else Ceiling(kitti, args.scans or 5, args.device, options)
        for rep in range(args.repeat):  # interleaved: a host's drift touches every variant alike
            for label, extra in variants:
                for name, argv in (("kitti", [str(kitti / "velodyne"), "--poses", str(kitti / "poses.txt")]),
                                   ("av2", [str(av2)])):
                    key = f"{name}+{label}" if label else name
                    env = dict(w.split("=", 1) for w in extra if _is_env(w))
                    cli_extra = [w for w in extra if not _is_env(w)]
                    saved = {k: os.environ.get(k) for k in env}
                    os.environ.update(env)
                    try:
                        t_start = time.time()
                        wall, summ = run_cli(["run", *argv, "--out", str(tmp / f"out_{key}_{rep}"), *common,
                                              *cli_extra])
                        windows.append({"name": f"{key} (run {rep + 1})", "t0": t_start, "t1": time.time()})
                    finally:
                        # ~2.5 MB a frame: 3 repeats x 4 variants x 768 frames filled a 64 GiB disk (F6)
                        shutil.rmtree(tmp / f"out_{key}_{rep}", ignore_errors=True)
                        for k, v in saved.items():
                            if v is None:
                                os.environ.pop(k, None)
                            else:
                                os.environ[k] = v
                    r = {"wall_s": wall, "frames_per_s": summ["written"] / wall, "summary": summ,
                         "run_args": " ".join(common[2:] + extra)}
                    # the steady part: from the last engine's first frame on (engines_start, a run
                    # on several engines); its window lets host_sampler give the steady GPU busy share
                    st = summ.get("engines_start") or {}
                    steady = ""
                    if st.get("frames_per_s_after_join"):
                        r["steady_frames_per_s"] = st["frames_per_s_after_join"]
                        r["all_joined_s"] = st["all_joined_s"]
                        windows.append({"name": f"{key} (run {rep + 1}) steady",
                                        "t0": st["run_started_at"] + st["all_joined_s"],
                                        "t1": st["run_started_at"] + st["last_frame_s"]})
                        steady = (f"; {r['steady_frames_per_s']:.1f} after all {len(st['first_frame_s'])} engines "
                                  f"had joined ({st['all_joined_s']:.2f} s)")
                    reps.setdefault(key, []).append(r)
                    print(f"  {key} (run {rep + 1}): {r['frames_per_s']:.1f} frames/s{steady}", flush=True)
            if ceil_runs is None:
                continue
            # the ceiling in the same repetition: each run's ratio to it is taken at the same time
            c = args.frames / ceil_runs.time()
            for runs in reps.values():
                runs[-1]["ceiling_frames_per_s"] = c
                runs[-1]["ratio_to_ceiling"] = c / runs[-1]["frames_per_s"]
            print(f"  ceiling (run {rep + 1}): {c:.1f} frames/s", flush=True)
        for key, runs in reps.items():  # the median run (an odd count: a real run)
            order = sorted(runs, key=lambda r: r["frames_per_s"])
            rows[key] = dict(order[(len(order) - 1) // 2], repeats_frames_per_s=[r["frames_per_s"] for r in runs],
                             repeats_steady_frames_per_s=[r.get("steady_frames_per_s") for r in runs],
                             repeats_ratio_to_ceiling=[r.get("ratio_to_ceiling", NAN) for r in runs],
                             # each run against the ceiling timed in its own repetition: the median
                             ratio_to_ceiling=statistics.median(r.get("ratio_to_ceiling", NAN) for r in runs))
        ceil = ceil_runs.summary() if ceil_runs is not None else None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    n = args.frames
    window = args.scans or "each preset's"
    print(f"\nfloxels run end to end on {args.device} ({n} frames, {window} scans; input+LABEL: with that "
          f"--variant's arguments)")
    hdr = ("input", "workers", "frames/s", "ms/frame", "read", "preproc", "transform", "estimate", "compute", "write",
           "wait in", "deliver", "setup", "idle dev", "host %", "vs ceiling")
    print(" | ".join(f"{h:>9}" for h in hdr))
    # workers: N readers, t(hread)/p(rocess), where preprocessing ran, writers t/p
    for name, r in rows.items():
        # with --engines N the summary sums each stage over the engines: per engine here
        engines = r["summary"].get("engines", 1)
        st = {k: v / engines for k, v in r["summary"]["stages_s"].items()}
        host_pct = 100 * (r["wall_s"] - st["compute"]) / r["wall_s"]  # everything but the method computing
        r["host_pct"] = host_pct
        sm = r["summary"]
        vals = [name, f"{sm['workers']}{sm['worker_kind'][0]}/{sm['preprocess_device']}/w{sm.get('writer_kind', 'thread')[0]}"
                + (f"x{engines}" if engines > 1 else ""), f"{r['frames_per_s']:.1f}", f"{1e3 * r['wall_s'] / n:.1f}"] + \
            [f"{1e3 * st.get(k, 0.0) / n:.1f}" for k in ("read", "preprocess", "transform", "estimate", "compute",
                                                          "write", "wait_input", "deliver")] + \
            [f"{1e3 * (r['wall_s'] - st['wall']) / n:.1f}", f"{1e3 * (r['wall_s'] - st['compute']) / n:.1f}", f"{host_pct:.1f}", f"{r['ratio_to_ceiling']:.2f}x"]
        print(" | ".join(f"{v:>9}" for v in vals))
    if args.repeat > 1:
        for name, r in rows.items():
            print(f"{name}: frames/s of the {args.repeat} runs: " + ", ".join(f"{v:.1f}" for v in r["repeats_frames_per_s"])
                  + " (ceiling: " + ", ".join(f"{v:.1f}" for v in (ceil or {}).get("repeats_frames_per_s", [])) + "; ratios: "
                  + ", ".join(f"{v:.2f}x" for v in r["repeats_ratio_to_ceiling"]) + ")")
    for name, r in rows.items():
        base = rows[name.split("+")[0]]
        if r is not base:
            print(f"{name}: {r['frames_per_s'] / base['frames_per_s']:.2f}x the default run of the same input")
    print("(stage columns: ms per frame; read/preproc/transform/write are summed over worker threads and overlap "
          "the estimate; 'deliver': the optimiser thread handing results to the writers; 'setup': the command's "
          "time outside the pipeline (arguments, finding frames and poses, summary); 'idle dev' = wall - compute: "
          "time the method was not computing; 'vs ceiling': the median over repetitions of the ceiling timed in "
          "that repetition / the run's frames/s)")
    if ceil is not None:
        print(f"ceiling: estimate_sequence on the {n} prepared scans in memory: {ceil['frames_per_s']:.1f} frames/s "
              f"({1e3 * ceil['estimate_s'] / n:.1f} ms/frame); serial host work it excludes: read "
              f"{ceil['serial_read_ms']:.1f} + preprocess {ceil['serial_preprocess_ms']:.1f} ms/frame (the CPU op, one thread)")
    res = {"device": args.device, "gpu": torch.cuda.get_device_name() if args.device.startswith("cuda") else None,
           "frames": n, "beams": args.beams, "repeat": args.repeat, "gil_switch_interval": args.gil_switch_interval, "raw_points": npts, "scans": args.scans, "max_iters": args.max_iters,
           "runs": {k: {kk: vv for kk, vv in v.items()} for k, v in rows.items()}, "ceiling": ceil}
    if args.windows:
        args.windows.write_text(json.dumps(windows, indent=1) + "\n")
    path = Path(args.json or Path(__file__).parent / "results" / f"bench_run_{args.device.split(':')[0]}.json")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(res, indent=2, default=str) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
