"""Frames/s of ``floxels run DATASET`` run locally and through Ray, on the same simulated dataset.

    python bench/bench_ray.py                      # CPU: local vs Ray 1 worker vs Ray 2 workers (~2 min, 2 cores)
    python bench/bench_ray.py --device cuda        # 1 GPU: local vs Ray 1 task/GPU vs 2 tasks sharing it (0.5 GPU each)
    python bench/bench_ray.py --device cuda --gpus 1 2 4 8     # scaling over GPUs of one host (issue 19 defaults:
                                                   # 16 sequences x 64 frames, 128 beams)

Every mode gets the same resources: the local run uses all CPU threads (and one GPU); Ray gets the
same CPUs (and GPUs), split evenly between its concurrent tasks. Each mode is warmed up first on
a tiny dataset (worker processes started, torch and the extension loaded), as in a long job where
that start is paid once. Ray's overhead is its wall time over the local run's at equal resources.
Every Ray output tree is compared with the local run's (flow max |difference|, masks equal).
With ``--gpus``: one Ray run per GPU count (``CUDA_VISIBLE_DEVICES`` = the first k GPUs, one task
per GPU), scaling efficiency = frames/s / (k x frames/s on 1 GPU), the host CPU share during the
run (``/proc/stat``), and each output tree compared with the 1-GPU run's.
Prints a table and writes JSON (bench/results/bench_ray_<device>[_gpus].json).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from contextlib import redirect_stderr
from io import StringIO
from pathlib import Path

import numpy as np

SCENES = ("urban", "crossing", "highway", "parking")


def _simulate_one(job):
    from floxels_ext.evaluation.seqio import save_sequence
    from floxels_ext.evaluation.sim import simulate_sequence

    d, scene, frames, seed, beams, az = job
    save_sequence(d, simulate_sequence(scene, frames, seed, beams=beams, azimuth_steps=az))
    return d


def make_dataset(root: Path, sequences: int, frames: int, beams: int, az: int, procs: int) -> Path:
    """``sequences`` simulated sequences (``floxels simulate`` layout) under root; reused when present."""
    stamp = root / "bench_dataset.json"
    want = dict(sequences=sequences, frames=frames, beams=beams, azimuth_steps=az)
    if stamp.is_file() and json.loads(stamp.read_text()) == want:
        return root
    shutil.rmtree(root, ignore_errors=True)
    jobs = [(root / f"seq{k:03d}", SCENES[k % len(SCENES)], frames, k, beams, az) for k in range(sequences)]
    with ProcessPoolExecutor(max(1, procs)) as ex:
        list(ex.map(_simulate_one, jobs))
    stamp.write_text(json.dumps(want))
    return root


class CpuShare:
    """Busy share of all the host's CPUs between start() and stop(), from /proc/stat (Linux)."""

    @staticmethod
    def _read():
        try:
            with open("/proc/stat") as f:
                v = [int(x) for x in f.readline().split()[1:]]
        except OSError:
            return None
        idle = v[3] + (v[4] if len(v) > 4 else 0)
        return sum(v), idle

    def start(self):
        self.a = self._read()

    def stop(self) -> float | None:
        b = self._read()
        if self.a is None or b is None or b[0] == self.a[0]:
            return None
        return 1.0 - (b[1] - self.a[1]) / (b[0] - self.a[0])


def run_job(data: Path, out: Path, flags: list[str], extra: list[str]) -> tuple[float, int, float | None, str]:
    """(wall s, rc, host CPU share, stderr) of one ``floxels run`` of the dataset."""
    from floxels_ext import cli

    shutil.rmtree(out, ignore_errors=True)
    err = StringIO()
    share = CpuShare()
    share.start()
    t0 = time.perf_counter()
    with redirect_stderr(err):
        rc = cli.main(["run", str(data), "--out", str(out), *flags, *extra])
    wall = time.perf_counter() - t0
    return wall, rc, share.stop(), err.getvalue()


def best_of(repeats: int, data: Path, out: Path, flags: list[str], extra: list[str]):
    """run_job ``repeats`` times (from an empty output each time); the fastest run's figures."""
    return min((run_job(data, out, flags, extra) for _ in range(max(1, repeats))), key=lambda r: r[0])


def compare_trees(out: Path, ref: Path) -> dict:
    names = sorted(p.relative_to(ref) for p in ref.rglob("*.npz"))
    got = sorted(p.relative_to(out) for p in out.rglob("*.npz"))
    if names != got:
        return dict(same_files=False, files=len(got), ref_files=len(names))
    norms, masks = [], True
    for rel in names:
        with np.load(out / rel) as a, np.load(ref / rel) as b:
            masks &= bool(np.array_equal(a["mask"], b["mask"]))
            d = np.linalg.norm(a["flow"] - b["flow"], axis=1)
            norms.append(d[np.isfinite(d)])
    d = np.concatenate(norms) if norms else np.zeros(0)
    # on CUDA two runs of the same input differ (float atomics; the lowest-loss iteration can
    # change): the distribution, not only the maximum, says whether Ray changed anything
    return dict(same_files=True, files=len(names), max_flow_diff=float(d.max()) if d.size else 0.0,
                p999_flow_diff=float(np.quantile(d, 0.999)) if d.size else 0.0,
                frac_over_1cm=float((d > 0.01).mean()) if d.size else 0.0, masks_equal=masks)


def start_ray(num_cpus: int, num_gpus: int, address: str | None):
    import ray

    if ray.is_initialized():
        ray.shutdown()
    t0 = time.perf_counter()
    if address:
        ray.init(address=address, log_to_driver=False)
    else:
        ray.init(address="local", num_cpus=num_cpus, num_gpus=num_gpus, include_dashboard=False,
                 log_to_driver=False, _node_ip_address="127.0.0.1")
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--gpus", type=int, nargs="+", help="GPU counts for the scaling series (Ray, one task per GPU)")
    ap.add_argument("--sequences", type=int, help="default: 4 (cpu), 8 (cuda), 16 (--gpus)")
    ap.add_argument("--frames", type=int, help="frames per sequence; default: 6 (cpu), 32 (cuda), 64 (--gpus)")
    ap.add_argument("--beams", type=int, help="lidar beams; default: 32 (cpu), 64 (cuda), 128 (--gpus)")
    ap.add_argument("--azimuth-steps", type=int, help="default: 512 (cpu), 2048 (cuda)")
    ap.add_argument("--max-iters", type=int, help="optimiser iterations (default: 30 on cpu, the method's 500 on cuda)")
    ap.add_argument("--task-frames", type=int, default=0, help="frames per Ray task (0: whole sequences)")
    ap.add_argument("--cpus", type=int, default=os.cpu_count(), help="CPUs for every mode (default: all)")
    ap.add_argument("--modes", nargs="+", default=["local", "ray1", "ray2"],
                    help="local, local2 (a second local run: the run-to-run noise floor), ray1 (1 task at a time, all "
                         "CPUs, 1 GPU), ray2 (2 tasks, half each); without --gpus")
    ap.add_argument("--ray-address", help="use this running cluster instead of a local one (--gpus: nodes' GPUs)")
    ap.add_argument("--data", type=Path, help="dataset directory (made if missing or different; default: temporary)")
    ap.add_argument("--repeats", type=int, default=1, help="runs per mode (interleaved), the fastest counts")
    ap.add_argument("--json", help="output JSON path")
    args = ap.parse_args()

    cuda = args.device == "cuda"
    scale = args.gpus is not None
    seqs = args.sequences or (16 if scale else 8 if cuda else 4)
    frames = args.frames or (64 if scale else 32 if cuda else 6)
    beams = args.beams or (128 if scale else 64 if cuda else 32)
    az = args.azimuth_steps or (2048 if cuda else 512)
    cpus = max(1, args.cpus)
    flags = ["--device", args.device]
    if args.max_iters or not cuda:
        flags += ["--max-iters", str(args.max_iters or 30)]
    if scale and not cuda:
        sys.exit("--gpus needs --device cuda")
    if cuda:
        import torch

        if not torch.cuda.is_available():
            sys.exit("--device cuda: no CUDA device")
        n_gpu = torch.cuda.device_count()
        if scale and max(args.gpus) > n_gpu and not args.ray_address:
            sys.exit(f"--gpus {max(args.gpus)}: this host has {n_gpu} GPU(s)")
    tmp = Path(tempfile.mkdtemp(prefix="bench_ray_"))
    data = args.data or tmp / "data"
    t0 = time.perf_counter()
    make_dataset(data, seqs, frames, beams, az, cpus)
    warm = make_dataset(tmp / "warm", 2, 3, 16, 360, 1)
    n_frames = seqs * frames
    print(f"dataset: {seqs} sequences x {frames} frames, {beams} beams x {az} azimuth steps "
          f"(simulated in {time.perf_counter() - t0:.1f} s); {cpus} CPUs; {' '.join(flags)}", flush=True)

    import torch

    torch.set_num_threads(cpus)
    rows = []
    ref = tmp / "out_local"

    def record(name, wall, rc, share, err, compare_to=None, **kw):
        row = dict(mode=name, wall_s=wall, rc=rc, frames=n_frames, fps=n_frames / wall, cpu_share=share, **kw)
        if compare_to is not None and compare_to.is_dir():
            row.update(compare_trees(tmp / f"out_{name}", compare_to))
        if rc != 0:
            row["stderr_tail"] = err[-2000:]
        rows.append(row)
        print(f"  {name:<14} {wall:8.2f} s  {row['fps']:8.2f} frames/s  rc {rc}", flush=True)
        return row

    workers = {"local": 1, "local2": 1, "ray1": 1, "ray2": 2}  # local2: a second local run, the noise floor
    if not scale:
        bad = [m for m in args.modes if m not in workers]
        if bad:
            sys.exit(f"unknown --modes {bad}; choose from local local2 ray1 ray2")
        init_s = start_ray(cpus, 1 if cuda else 0, args.ray_address) if set(args.modes) - {"local"} else None
        extras = {}
        for mode in args.modes:
            w = workers[mode]
            extras[mode] = [] if mode.startswith("local") else \
                ["--ray", "--max-tasks", str(w), "--cpus-per-task", str(max(1, cpus // w)),
                 "--task-frames", str(args.task_frames)] + (["--gpus-per-task", f"{1.0 / w:g}"] if cuda else [])
            run_job(warm, tmp / f"warm_{mode}", flags, extras[mode])
        best: dict = {}
        for _ in range(max(1, args.repeats)):  # interleaved: a change of the machine's load hits every mode
            for mode in args.modes:
                r = run_job(data, tmp / f"out_{mode}", flags, extras[mode])
                if mode not in best or r[0] < best[mode][0]:
                    best[mode] = r
                if cuda:
                    torch.cuda.empty_cache()  # leave the GPU's memory to the Ray workers
        for mode in args.modes:
            record(mode, *best[mode], compare_to=None if mode == "local" else ref,
                   ray_init_s=None if mode.startswith("local") else init_s, workers=workers[mode], gpus=1 if cuda else 0)
    else:
        run_job(warm, tmp / "warm_local", flags, [])  # the local run: the reference of outputs and speed
        record("local", *best_of(args.repeats, data, ref, flags, []), gpus=1, workers=1)
        torch.cuda.empty_cache()
        base = None
        visible = os.environ.get("CUDA_VISIBLE_DEVICES")
        for k in args.gpus:
            if not args.ray_address:  # Ray sees (and its workers use) the first k GPUs
                os.environ["CUDA_VISIBLE_DEVICES"] = ",".join(str(i) for i in range(k))
            init_s = start_ray(cpus, k, args.ray_address)
            extra = ["--ray", "--gpus-per-task", "1", "--max-tasks", str(k), "--cpus-per-task", str(max(1, cpus // k)),
                     "--task-frames", str(args.task_frames)]
            run_job(warm, tmp / f"warm_gpus{k}", flags, extra)
            out = tmp / f"out_gpus{k}"
            row = record(f"gpus{k}", *best_of(args.repeats, data, out, flags, extra), compare_to=base or ref,
                         ray_init_s=init_s, workers=k, gpus=k)
            if k == 1 or base is None:
                base, fps1 = out, row["fps"] / k
            row["efficiency"] = row["fps"] / (k * fps1)
        if visible is None:
            os.environ.pop("CUDA_VISIBLE_DEVICES", None)
        else:
            os.environ["CUDA_VISIBLE_DEVICES"] = visible
    if "ray" in sys.modules:
        import ray

        ray.shutdown()

    local = next((r for r in rows if r["mode"] == "local"), None)
    print(f"\n{'mode':<10}{'workers':>8}{'GPUs':>6}{'wall s':>9}{'frames/s':>10}{'vs local':>10}{'CPU share':>11}"
          f"{'eff.':>7}{'max |dflow|':>13}{'p99.9':>10}{'>1 cm':>8}{'masks':>7}")
    for r in rows:
        if local is not None:
            r["overhead_vs_local"] = r["wall_s"] / local["wall_s"] - 1.0
        vs = f"{100 * r['overhead_vs_local']:+.1f}%" if local is not None and r is not local else "-"
        share = f"{100 * r['cpu_share']:.0f}%" if r.get("cpu_share") is not None else "-"
        eff = f"{r['efficiency']:.2f}" if "efficiency" in r else "-"
        diff = f"{r['max_flow_diff']:.2e}" if "max_flow_diff" in r else ("files differ" if "same_files" in r else "-")
        masks = ("yes" if r["masks_equal"] else "NO") if "masks_equal" in r else "-"
        p999 = f"{r['p999_flow_diff']:.1e}" if "p999_flow_diff" in r else "-"
        over = f"{100 * r['frac_over_1cm']:.2f}%" if "frac_over_1cm" in r else "-"
        print(f"{r['mode']:<10}{r['workers']:>8}{r['gpus']:>6}{r['wall_s']:>9.2f}{r['fps']:>10.2f}{vs:>10}"
              f"{share:>11}{eff:>7}{diff:>13}{p999:>10}{over:>8}{masks:>7}")
    dev_name = torch.cuda.get_device_name() if cuda else platform.processor() or platform.machine()
    result = dict(device=args.device, device_name=dev_name, cpus=cpus, sequences=seqs, frames_per_sequence=frames,
                  beams=beams, azimuth_steps=az, flags=flags, task_frames=args.task_frames, repeats=args.repeats,
                  load_average=os.getloadavg() if hasattr(os, "getloadavg") else None, rows=rows)
    path = Path(args.json or Path(__file__).parent / "results" / f"bench_ray_{args.device}{'_gpus' if scale else ''}.json")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=2) + "\n")
    print(f"\nwrote {path}")
    shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
