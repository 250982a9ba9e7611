"""Frames/s of ``floxels run DATASET`` (local and Ray) against one long sequence, on a dataset
shaped like a real one (issue 32).

    python bench/bench_ray.py                               # CPU-sized (4 x 12 frames, 32 beams)
    python bench/bench_ray.py --device cuda                 # 1 GPU: long sequence, dataset local, dataset on Ray
    python bench/bench_ray.py --device cuda --gpus 1 2      # + Ray on 1 and 2 GPUs (one worker per GPU)
    python bench/bench_ray.py --device cuda --gpus 1 2 4 --modes long ray --sequences 80 --ray-address auto \
        --cold 4 --subset 16 --subset-gpus 2                # issue 44 (tools/gpu_ray_bench.sh)
    python bench/bench_ray.py --device cuda --gpus 1 4 --workers-per-gpu 1 2 ...   # + rows of 2 workers a GPU

The dataset (``_kitti_dataset.py``): ``--sequences`` (default 16) sequences of ``--frames``
(150) frames in the KITTI odometry layout (.bin scans in their sensor frames, poses/NN.txt),
``--beams`` x ``--azimuth`` (128 x 1800: ~200k raw points a scan, ground included), ``--distinct``
of them simulated (8; the others are hard links: the same work), cached in ``--data``. The
reference is one long sequence holding the same frames (the distinct sequences one after the
other), run by the plain ``floxels run`` in the same process, on the same GPU, in the same call.

Rows (``--modes``): ``long`` (the plain run of the long sequence), ``local`` (``floxels run
DATASET``: one pipeline for every sequence), ``rayK`` (``--ray``, one worker per GPU, one row
per ``--gpus`` count; ``rayKxW``: W workers share each GPU, ``--workers-per-gpu``). Each is warmed up first on a tiny dataset; for Ray that job leaves its
workers in the warm pool (``--keep-workers``), so ``rayK`` rows measure warm workers (the
steady state and a warm cluster's start). ``coldK`` rows (``--cold K``) run the dataset with
fresh workers (``--keep-workers 0``: process, imports, CUDA context in the row), ``coldK/N`` and
``rayK/N`` the first N sequences (``--subset N``, on ``--subset-gpus``) fresh and warm.
Columns: frames/s over the command's wall time; ``first s``: seconds until the first output
file appeared; ``all 1st``: the slowest worker's first output (its timeline); frames/s from the
first output on; the per-GPU rate against the long sequence's (target >= 0.9); the scaling
efficiency (frames/s / (K x the 1-GPU warm Ray row's, of the same W)); ``workers``: those that
wrote frames / those asked for (fewer: some never started; each Ray row starts with the cluster
free, the pool retired). Below the table, each worker's start
timeline (from the job's ``ray_job_summary.json``: s from the driver's start of the job). The
Ray outputs are compared with the local run's (two sequences, flow max |difference|). Prints a
table and writes JSON (bench/results/bench_ray_<device>.json or --json).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import threading
import time
from contextlib import redirect_stderr
from io import StringIO
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _kitti_dataset import make_kitti_dataset  # noqa: E402


class FirstOutput(threading.Thread):
    """Seconds from start until ``out`` holds an output file (polled every 20 ms)."""

    def __init__(self, out: Path) -> None:
        super().__init__(daemon=True)
        self.out, self.t0, self.first, self.stop = out, time.perf_counter(), None, False

    def run(self) -> None:
        while not self.stop and self.first is None:
            if self.out.is_dir() and next(self.out.rglob("*.npz"), None) is not None:
                self.first = time.perf_counter() - self.t0
            time.sleep(0.02)


def run_job(argv: list[str], out: Path) -> dict:
    from floxels_ext import cli

    shutil.rmtree(out, ignore_errors=True)
    err = StringIO()
    watch = FirstOutput(out)
    watch.start()
    t0, t0_wall = time.perf_counter(), time.time()
    with redirect_stderr(err):
        rc = cli.main([argv[0], argv[1], "--out", str(out), *argv[2:]])
    wall = time.perf_counter() - t0
    watch.stop = True
    watch.join()
    frames = sum(1 for _ in out.rglob("*.npz"))
    row_steady = steady_fps(out)
    # t0/t1 (time.time()): the row's span, for tools/host_sampler.py's per-row summary
    row = dict(rc=rc, wall_s=wall, frames=frames, fps=frames / wall, first_output_s=watch.first,
               t0=t0_wall, t1=t0_wall + wall, fps_steady=row_steady)
    if watch.first is not None and wall > watch.first:
        row["fps_after_first"] = frames / (wall - watch.first)
    if rc != 0:
        row["stderr_tail"] = err.getvalue()[-3000:]
    return row


def steady_fps(out: Path) -> float | None:
    """Frames/s between the 10th and the 90th percentile of the outputs' write times: the steady
    state, without the workers' start or the tail where some have finished (rows whose starts
    differ, fresh processes against warm workers, compare on it)."""
    t = sorted(p.stat().st_mtime for p in out.rglob("*.npz"))
    if len(t) < 20:
        return None
    a, b = int(0.1 * len(t)), int(0.9 * len(t))
    return (b - a) / (t[b] - t[a]) if t[b] > t[a] else None


def run_procs(data: Path, seqs: int, k: int, w: int, flags: list[str], cpus: int, out: Path, engines: int = 1) -> dict:
    """The control without Ray: k x w independent plain ``floxels run`` processes, w of them on
    each of k GPUs (CUDA_VISIBLE_DEVICES), each over every (k x w)-th sequence (a list file), each
    with cpus / (k x w) CPU threads. Whatever Ray adds (or takes) is the gap to the rayKxW row;
    what the host loses to more processes is the gap between this row's steady rate and k x the
    1-GPU one. Fresh processes: compare the steady rate (fps_steady), not the wall's.
    ``engines`` E > 1: w / E processes a GPU, each ``--engines E`` (one process's engines share
    a GPU as w Ray workers do): the layout of one Ray worker a GPU running local engines."""
    import subprocess

    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    w = max(1, w // engines)
    flags = [*flags, "--engines", str(engines)]
    n = k * w
    threads = str(max(1, cpus // n))
    procs, t0, t0_wall = [], time.perf_counter(), time.time()
    for i in range(n):
        lst = sequence_list(data, out / f"list{i}.txt", range(i, seqs, n))
        env = dict(os.environ, CUDA_VISIBLE_DEVICES=str(i // w), OMP_NUM_THREADS=threads, MKL_NUM_THREADS=threads)
        procs.append(subprocess.Popen([sys.executable, "-m", "floxels_ext", "run", str(lst), "--out", str(out / f"p{i}"),
                                       *flags], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True))
    errs = [p.communicate()[1] for p in procs]
    wall = time.perf_counter() - t0
    frames = sum(1 for _ in out.rglob("*.npz"))
    row = dict(rc=max(p.returncode for p in procs), wall_s=wall, frames=frames, fps=frames / wall,
               first_output_s=None, t0=t0_wall, t1=t0_wall + wall, fps_steady=steady_fps(out))
    if row["rc"] != 0:
        row["stderr_tail"] = "".join(e[-1500:] for e, p in zip(errs, procs) if p.returncode != 0)[-3000:]
    shutil.rmtree(out, ignore_errors=True)
    return row


def compare(out: Path, ref: Path, rels: list[str]) -> dict:
    diffs, masks, n = [], True, 0
    for rel in rels:
        for p in sorted((ref / rel).glob("*.npz")):
            with np.load(p) as b, np.load(out / rel / p.name) as a:
                masks &= bool(np.array_equal(a["mask"], b["mask"]))
                d = np.linalg.norm(a["flow"] - b["flow"], axis=1)
                diffs.append(d[np.isfinite(d)])
                n += 1
    d = np.concatenate(diffs) if diffs else np.zeros(0)
    # the distribution, not only the maximum, says whether Ray changed anything (on the CPU: 0)
    return dict(compared_frames=n, max_flow_diff=float(d.max()) if d.size else 0.0,
                frac_over_1cm=float((d > 0.01).mean()) if d.size else 0.0, masks_equal=masks)


def job_info(out: Path) -> dict:
    """The job's ray_job_summary.json (driver-written), {} when there is none."""
    try:
        return json.loads((out / "ray_job_summary.json").read_text())
    except (OSError, ValueError):
        return {}


def job_workers(out: Path) -> list[dict]:
    """Each worker's start timeline etc. from the job's ray_job_summary.json."""
    info = job_info(out)
    keep = ("name", "host", "pid", "gpus", "warm", "claimed", "written", "streams", "timeline",
            "threads", "warm_error", "cuda_devices")
    return [{k: w.get(k) for k in keep} for w in info.get("workers", [])]


def sequence_list(data: Path, path: Path, indices) -> Path:
    """A list file of the dataset's sequences ``indices`` (KITTI poses given per line)."""
    path.write_text("".join(f"{data}/sequences/{i:02d}/velodyne --poses {data}/poses/{i:02d}.txt\n"
                            for i in indices))
    return path


def subset_list(data: Path, seqs: int, n: int) -> Path:
    """A list file of the dataset's first ``n`` sequences."""
    n = min(n, seqs)
    return sequence_list(data, data / f"first{n}.txt", range(n))


def retire_pool() -> None:
    """The warm pool's idle workers exit (their GPUs free for whatever runs next)."""
    import ray

    for a in ray.util.list_named_actors(all_namespaces=True):
        if a["namespace"] == "floxels":
            try:
                ray.get(ray.get_actor(a["name"], namespace="floxels").retire.remote(), timeout=10)
            except (ValueError, ray.exceptions.RayError):
                pass


def free_cluster(timeout: float = 90.0) -> float:
    """Retires the pool and waits until every GPU and CPU of the cluster is free again (a row then
    starts from the same state whatever ran before it, e.g. workers of another size); seconds waited."""
    import ray

    t0 = time.perf_counter()
    retire_pool()
    total = ray.cluster_resources()
    while time.perf_counter() - t0 < timeout:
        free = ray.available_resources()
        if all(free.get(k, 0.0) >= total.get(k, 0.0) - 1e-6 for k in ("GPU", "CPU")):
            break
        time.sleep(0.25)
    else:
        print(f"  (cluster not free after {timeout:.0f} s: {ray.available_resources()} of {total})", flush=True)
    return time.perf_counter() - t0


def settle_pool(n: int, timeout: float = 30.0) -> float:
    """Waits until the warm pool holds ``n`` idle workers (a warm-up job can end before all of
    its workers are up: those still starting, or still inside the dropped job's ``run``, would
    then start inside the measured row, E6); seconds waited."""
    import ray

    t0 = time.perf_counter()
    while time.perf_counter() - t0 < timeout:
        idle = 0
        for a in ray.util.list_named_actors(all_namespaces=True):
            if a["namespace"] != "floxels":
                continue
            try:
                idle += bool(ray.get(ray.get_actor(a["name"], namespace="floxels").info.remote(), timeout=5)["idle"])
            except (ValueError, KeyError, ray.exceptions.RayError):
                pass
        if idle >= n:
            break
        time.sleep(0.25)
    else:
        print(f"  (the pool has fewer than {n} idle workers after {timeout:.0f} s)", flush=True)
    return time.perf_counter() - t0


def start_ray(cpus: int, gpus: int, address: str | None) -> float:
    import ray

    if ray.is_initialized():
        ray.shutdown()
    t0 = time.perf_counter()
    if address:
        ray.init(address=address, log_to_driver=False)
    else:
        ray.init(address="local", num_cpus=cpus, num_gpus=gpus, include_dashboard=False, log_to_driver=False,
                 _node_ip_address="127.0.0.1")
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--gpus", type=int, nargs="+", help="GPU counts of the Ray rows (default: 1)")
    ap.add_argument("--sequences", type=int, help="default 16 (cuda), 4 (cpu)")
    ap.add_argument("--frames", type=int, help="frames per sequence; default 150 (cuda), 12 (cpu)")
    ap.add_argument("--distinct", type=int, default=8, help="sequences simulated; the others link to them (default 8)")
    ap.add_argument("--beams", type=int, help="default 128 (cuda), 32 (cpu)")
    ap.add_argument("--azimuth", type=int, help="azimuth steps; default 1800 (cuda), 512 (cpu)")
    ap.add_argument("--max-iters", type=int, help="optimiser iterations (default: 30 on cpu, the method's on cuda)")
    ap.add_argument("--modes", nargs="+", default=["long", "local", "ray"], choices=["long", "local", "ray", "procs"],
                    help="procs: the control without Ray, K x W plain floxels run processes (run_procs)")
    ap.add_argument("--cpus", type=int, default=os.cpu_count(), help="CPUs for Ray (default: all)")
    ap.add_argument("--run-args", default="", help="extra floxels run arguments for every row (quoted)")
    ap.add_argument("--ray-address", help="a running cluster instead of a local one")
    ap.add_argument("--cold", type=int, nargs="*", default=[], metavar="K",
                    help="GPU counts of extra rows 'coldK': the dataset with fresh workers (--keep-workers 0), their "
                         "start included (the 'rayK' rows take the warm workers a tiny job has just started)")
    ap.add_argument("--subset", type=int, metavar="N", help="also run the first N sequences (a list file) with fresh "
                    "workers ('coldK/N') and warm ones ('rayK/N') on each of --subset-gpus")
    ap.add_argument("--subset-gpus", type=int, nargs="+", default=[2], metavar="K", help="default 2")
    ap.add_argument("--workers-per-gpu", type=int, nargs="+", default=[1], metavar="W",
                    help="Ray rows with W workers sharing each GPU (--gpus-per-task 1/W; rows ray<K>x<W> for W > 1; "
                         "each W's efficiency against its own 1-GPU row; the cold and subset rows use the first W). "
                         "Default 1")
    ap.add_argument("--procs-engines", type=int, nargs="+", default=[1], metavar="E",
                    help="procs rows with W/E processes a GPU of --engines E each (rows procs<K>x<W>e<E> for E > 1; "
                         "default 1: W single-engine processes a GPU, like the W Ray workers)")
    ap.add_argument("--data", type=Path, help="dataset directory (made if missing or different; default: temporary)")
    ap.add_argument("--compare", type=int, default=2, help="sequences whose Ray outputs are compared (default 2)")
    ap.add_argument("--rounds", type=int, default=1, help="repeat the Ray (and procs) rows this many times, "
                    "interleaved (rows named #2, #3...): a host's noise against a real difference")
    ap.add_argument("--json", help="output JSON path")
    args = ap.parse_args()

    cuda = args.device == "cuda"
    seqs = args.sequences or (16 if cuda else 4)
    frames = args.frames or (150 if cuda else 12)
    beams = args.beams or (128 if cuda else 32)
    az = args.azimuth or (1800 if cuda else 512)
    gpus = args.gpus or [1]
    cpus = max(1, args.cpus)
    if min(args.workers_per_gpu) < 1:
        sys.exit("--workers-per-gpu: each value must be >= 1")
    import torch

    if cuda and not torch.cuda.is_available():
        sys.exit("--device cuda: no CUDA device")
    if cuda and "ray" in args.modes and max(gpus) > torch.cuda.device_count() and not args.ray_address:
        sys.exit(f"--gpus {max(gpus)}: this host has {torch.cuda.device_count()} GPU(s)")
    tmp = Path(tempfile.mkdtemp(prefix="bench_ray_"))
    data = args.data or tmp / "data"
    t0 = time.perf_counter()
    desc = make_kitti_dataset(data, seqs, frames, beams, az, cpus, args.distinct)
    warm = tmp / "warm"
    # the warm-up jobs: a task per worker, so every worker of a Ray row starts (and stays in the pool)
    most = max([2, *(args.gpus or [1]), *args.cold, *args.subset_gpus]) * max(args.workers_per_gpu)
    make_kitti_dataset(warm, most, 6, 16, 360, 2, 2)
    gen_s = time.perf_counter() - t0
    # the paper preset unless --run-args says otherwise (floxels run's default is accurate since issue 42)
    flags = ["--device", args.device, "-q", "--preset", "paper", *args.run_args.split()]
    if args.max_iters or not cuda:
        flags += ["--max-iters", str(args.max_iters or 30)]
    n_long = desc["distinct"] * frames
    print(f"dataset: {seqs} sequences x {frames} frames ({desc['distinct']} distinct), {beams} beams x {az} azimuth "
          f"steps, KITTI layout; long sequence: {n_long} frames; made in {gen_s:.1f} s; {' '.join(flags)}", flush=True)
    sel = ["--sequences", "sequences/*/velodyne"]

    def long_argv(root):
        return ["run", str(root / "long" / "velodyne"), "--poses", str(root / "long" / "poses.txt")]

    rows = []

    def record(name, row, **kw):
        row.update(mode=name, **kw)
        rows.append(row)
        print(f"  {name:<10} {row['wall_s']:8.2f} s  {row['fps']:8.2f} frames/s  rc {row['rc']}", flush=True)
        return row

    long = local = None
    if "long" in args.modes:
        run_job(long_argv(warm) + flags, tmp / "warm_long")
        long = record("long", run_job(long_argv(data) + flags, tmp / "out_long"), gpus=1)
        shutil.rmtree(tmp / "out_long", ignore_errors=True)  # outputs are GBs at full size
    if "local" in args.modes:
        run_job(["run", str(warm), *sel, *flags], tmp / "warm_local")
        local = record("local", run_job(["run", str(data), *sel, *flags], tmp / "out_local"), gpus=1)
    if "ray" in args.modes:
        if cuda:
            torch.cuda.empty_cache()  # leave the GPU's memory to the Ray workers
        visible = os.environ.get("CUDA_VISIBLE_DEVICES")
        subset = subset_list(data, seqs, args.subset) if args.subset else None
        # in --gpus order (a run cut by its time limit keeps the rows asked for first), then the others
        counts = list(dict.fromkeys(gpus + args.cold + (args.subset_gpus if subset else []))) if cuda else [1]
        gpus = gpus if cuda else [1]
        bases = {}
        for rnd, k in [(r, k) for r in range(max(1, args.rounds)) for k in counts]:
            if rnd and (k not in gpus or (k == 1 and len(gpus) > 1)):  # the 1-GPU base (the longest row) once
                continue
            sfx = f"#{rnd + 1}" if rnd else ""
            if cuda and not args.ray_address:  # Ray sees (and its workers use) the first k GPUs
                os.environ["CUDA_VISIBLE_DEVICES"] = ",".join(str(i) for i in range(k))
            init_s = start_ray(cpus, k if cuda else 0, args.ray_address)
            for wi, w in enumerate(args.workers_per_gpu if cuda else [1]):
                n = k * w  # workers of the row; W > 1: W processes share each GPU (their idle gaps filled)
                extra = ["--ray", "--max-tasks", str(n), "--cpus-per-task", str(max(1, cpus // n))]
                extra += ["--gpus-per-task", "1" if w == 1 else f"{1 / w:.4f}"] if cuda else []
                cold = ["--keep-workers", "0"]
                tag = "" if w == 1 else f"x{w}"

                def ray_row(name, argv, out, **kw):
                    row = record(name, run_job(argv, out), gpus=k, ray_init_s=init_s, workers_per_gpu=w, **kw)
                    row["workers"] = job_workers(out)
                    info = job_info(out)
                    row["all_tasks_ended_s"] = info.get("all_tasks_ended_s")  # the driver knew
                    row["tasks_run"] = info.get("tasks_run")  # each task's frames, worker and end: the tail
                    row["workers_asked"] = n  # against those that wrote frames: fewer means some never started
                    row["workers_writing"] = sum(1 for x in row["workers"] if (x.get("written") or 0) > 0)
                    return row

                if k in args.cold and wi == 0:  # fresh workers: their whole start is in the row
                    free_cluster()
                    ray_row(f"cold{k}{tag}", ["run", str(data), *sel, *flags, *extra, *cold], tmp / f"out_cold{k}",
                            cold=True)
                    shutil.rmtree(tmp / f"out_cold{k}", ignore_errors=True)
                if subset and k in args.subset_gpus and wi == 0:
                    free_cluster()
                    name = f"cold{k}{tag}/{args.subset}"
                    ray_row(name, ["run", str(subset), *flags, *extra, *cold], tmp / "out_sub", cold=True,
                            subset=args.subset)
                    shutil.rmtree(tmp / "out_sub", ignore_errors=True)
                    run_job(["run", str(warm), *sel, *flags, *extra], tmp / f"warm_ray{k}")  # fills the pool
                    settle_pool(n)
                    ray_row(f"ray{k}{tag}/{args.subset}", ["run", str(subset), *flags, *extra], tmp / "out_sub",
                            subset=args.subset)
                    shutil.rmtree(tmp / "out_sub", ignore_errors=True)
                if k in gpus:  # warm workers (the pool the warm-up job filled): the steady state
                    freed = free_cluster()
                    run_job(["run", str(warm), *sel, *flags, *extra], tmp / f"warm_ray{k}")
                    settled = settle_pool(n)  # every worker of the row warm, as the row's name says
                    out = tmp / f"out_ray{k}"
                    row = ray_row(f"ray{k}{tag}{sfx}", ["run", str(data), *sel, *flags, *extra], out, freed_s=freed,
                                  settled_s=settled)
                    if local is not None:
                        row.update(compare(out, tmp / "out_local",
                                           [f"sequences/{i:02d}/velodyne" for i in range(args.compare)]))
                    shutil.rmtree(out, ignore_errors=True)
                    if k == 1:
                        bases.setdefault(w, row)
                    if "procs" in args.modes:  # the control without Ray, right after (same host state)
                        free_cluster()
                        if cuda:
                            torch.cuda.empty_cache()
                        for e in args.procs_engines:
                            record(f"procs{k}{tag}{'' if e == 1 else f'e{e}'}{sfx}",
                                   run_procs(data, seqs, k, w, flags, cpus, tmp / "out_procs", e),
                                   gpus=k, workers_per_gpu=w, engines=e)
        for r in rows:  # scaling efficiency against the same W's 1-GPU warm row (cold rows too: their start counts)
            base = bases.get(r.get("workers_per_gpu"))
            if r["mode"].startswith(("ray", "cold")) and base is not None:
                r["efficiency"] = r["fps"] / (r["gpus"] * base["fps"] / base["gpus"])
        retire_pool()
        if visible is None:
            os.environ.pop("CUDA_VISIBLE_DEVICES", None)
        else:
            os.environ["CUDA_VISIBLE_DEVICES"] = visible
        import ray

        ray.shutdown()

    if "procs" in args.modes and "ray" not in args.modes:  # the control alone
        for k in (gpus if cuda else [1]):
            for w in (args.workers_per_gpu if cuda else [1]):
                for e in args.procs_engines:
                    record(f"procs{k}" + ("" if w == 1 else f"x{w}") + ("" if e == 1 else f"e{e}"),
                           run_procs(data, seqs, k, w, flags, cpus, tmp / "out_procs", e), gpus=k, workers_per_gpu=w,
                           engines=e)
    # the steady rates' efficiency, per family (ray, procs) against its own 1-GPU row of the same W
    fam = lambda r: "procs" if r["mode"].startswith("procs") else "ray" if r["mode"].startswith("ray") else None  # noqa: E731
    base: dict = {}
    for r in rows:
        if fam(r) and r["gpus"] == 1 and "/" not in r["mode"]:
            base.setdefault((fam(r), r.get("workers_per_gpu"), r.get("engines", 1)), r)
    for r in rows:
        b = base.get((fam(r), r.get("workers_per_gpu"), r.get("engines", 1)))
        if fam(r) and "/" not in r["mode"] and b is not None and b.get("fps_steady") and r.get("fps_steady"):
            r["efficiency_steady"] = r["fps_steady"] / (r["gpus"] * b["fps_steady"])
    print(f"\n{'mode':<10}{'GPUs':>5}{'wall s':>9}{'frames':>8}{'frames/s':>10}{'first s':>9}{'all 1st':>8}"
          f"{'f/s after':>10}{'per GPU/long':>14}{'eff.':>7}{'workers':>8}{'max |dflow|':>13}{'>1 cm':>8}{'masks':>7}{'steady':>10}{'eff st.':>8}")
    for r in rows:
        if long is not None:
            r["per_gpu_vs_long"] = r["fps"] / r["gpus"] / long["fps"]
        first = f"{r['first_output_s']:.2f}" if r.get("first_output_s") is not None else "-"
        after = f"{r['fps_after_first']:.1f}" if "fps_after_first" in r else "-"
        ratio = f"{r['per_gpu_vs_long']:.3f}" if "per_gpu_vs_long" in r else "-"
        eff = f"{r['efficiency']:.3f}" if "efficiency" in r else "-"
        diff = f"{r['max_flow_diff']:.2e}" if "max_flow_diff" in r else "-"
        over = f"{100 * r['frac_over_1cm']:.2f}%" if "frac_over_1cm" in r else "-"
        masks = ("yes" if r["masks_equal"] else "NO") if "masks_equal" in r else "-"
        steady = f"{r['fps_steady']:.1f}" if r.get("fps_steady") else "-"
        eff_st = f"{r['efficiency_steady']:.3f}" if "efficiency_steady" in r else "-"
        wk = f"{r['workers_writing']}/{r['workers_asked']}" if "workers_asked" in r else "-"
        # the slowest worker's first output, s from the driver's start of the job (its timeline)
        firsts = [w["timeline"].get("first_output") for w in r.get("workers", []) if w.get("timeline")]
        r["all_first_output_s"] = max(firsts) if firsts and None not in firsts else None
        all1 = f"{r['all_first_output_s']:.2f}" if r["all_first_output_s"] is not None else "-"
        print(f"{r['mode']:<10}{r['gpus']:>5}{r['wall_s']:>9.2f}{r['frames']:>8}{r['fps']:>10.2f}{first:>9}{all1:>8}"
              f"{after:>10}{ratio:>14}{eff:>7}{wk:>8}{diff:>13}{over:>8}{masks:>7}{steady:>10}{eff_st:>8}")
    from floxels_ext.lidar.dataset.ray_report import format_timeline

    for r in rows:  # where each worker's start went (s from the job's start; negative: before it)
        for w in r.get("workers", []):
            kind = "warm" if w.get("claimed") else "fresh"
            print(f"  {r['mode']:<10} {w['name'][-8:]} ({kind}, GPU {','.join(w.get('gpus') or []) or '-'}, "
                  f"{w.get('written')} frames): {format_timeline(w['timeline'])}"
                  + (f"; warm-up failed: {w['warm_error']}" if w.get("warm_error") else ""))
    for r in rows:  # the tail: each GPU's last output, and the last tasks to end (frames, worker, when)
        ends: dict[str, float] = {}
        for w in r.get("workers", []):
            last = (w.get("timeline") or {}).get("last_output")
            for g in w.get("gpus") or ["-"]:
                if last is not None:
                    ends[g] = max(ends.get(g, last), last)
        if ends:
            print(f"  {r['mode']:<10} tail: last output by GPU " + ", ".join(f"{g} +{t:.2f}" for g, t in sorted(ends.items()))
                  + "; last tasks: " + ", ".join(f"{t['task'].rsplit(' frames ', 1)[-1]} ({t['worker'][-8:]}, "
                                                 f"+{t['ended_s']:.2f})" for t in (r.get("tasks_run") or [])[-4:]
                                                 if "ended_s" in t))
    for r in rows:
        if r["rc"] != 0:
            print(f"\n{r['mode']} failed (exit {r['rc']}):\n{r.get('stderr_tail', '')}")
    dev_name = torch.cuda.get_device_name() if cuda else "cpu"
    result = dict(device=args.device, device_name=dev_name, cpus=cpus, dataset=desc, long_frames=n_long,
                  generate_s=gen_s, flags=flags, rows=rows,
                  load_average=os.getloadavg() if hasattr(os, "getloadavg") else None)
    path = Path(args.json or Path(__file__).parent / "results" / f"bench_ray_{args.device}.json")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=2) + "\n")
    print(f"\nwrote {path}")
    shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
