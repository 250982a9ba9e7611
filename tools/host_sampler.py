"""What a host's cores, GPUs and page cache do while a job runs (issue 44: why 4 GPUs collapse).

Runs beside a job and samples every ``--interval`` seconds, until ``--stop-file`` appears or
``--duration`` passes:

* the whole host: CPU busy share and steal (/proc/stat), load average, page cache dirty/writeback
  (MB), and a core's speed (``probe_ms``: a fixed single-threaded workload timed each sample, best
  of 3: the same work taking longer in a row means slower cores, whatever /proc/cpuinfo says);
* every process whose command line matches ``--match`` (regex; default: Ray's floxels workers
  and the python driver): its CPU (cores), its thread count, how many of its threads used more
  than 0.2 / 0.8 of a core, its main thread's share (the thread that feeds the GPU);
* every GPU: utilisation (%) and memory, from ``nvidia-smi --query-gpu`` (when present).

With ``--spy N`` (and ``py-spy`` on the PATH), a process with a thread at >= 0.8 of a core for 6
samples in a row gets one ``py-spy dump --native`` (all its threads' stacks) in
``OUT/spy/<pid>.txt``, at most N processes: what a busy-looping or saturated thread runs.

Writes every sample as JSON lines to ``OUT/samples.jsonl`` and, with ``--windows FILE`` (a
JSON list of {"name", "t0", "t1"} in time.time() seconds, e.g. the rows bench_ray.py records),
a per-window summary to ``OUT/summary.json`` and stdout. Measurement only: nothing of the
package imports it.

    python tools/host_sampler.py --out OUT --stop-file OUT/stop &   # then run the job
    touch OUT/stop; python tools/host_sampler.py --summarise OUT --windows rows.json
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import threading
import time
from pathlib import Path

HZ = os.sysconf("SC_CLK_TCK")
DEFAULT_MATCH = r"FloxelsWorker|floxels|bench_ray|bench_run|ray::IDLE|raylet|gcs_server"


def _cpu_total() -> tuple[int, int, int]:
    """(all ticks, idle ticks, steal ticks) of the host: steal is time the hypervisor gave this
    VM's cores to someone else (a VM's cores that slow down together show it)."""
    with open("/proc/stat") as f:
        vals = [int(v) for v in f.readline().split()[1:]]
    idle = vals[3] + vals[4]
    return sum(vals), idle, vals[7] if len(vals) > 7 else 0


def _probe_ms() -> float:
    """Milliseconds of a fixed single-threaded workload (Python loop + a small numpy sort): a
    core's speed as this process sees it. /proc/cpuinfo reads a flat clock on these VMs, so the
    clock's fall (or shared caches, memory bandwidth, steal) under load shows here instead."""
    import numpy as np

    t0 = time.perf_counter()
    acc = 0
    for i in range(20000):
        acc += i * i
    a = np.arange(32768, dtype=np.float64)[::-1].copy()
    a.sort()
    return 1000.0 * (time.perf_counter() - t0)


def _meminfo() -> dict:
    out = {}
    with open("/proc/meminfo") as f:
        for line in f:
            k, v = line.split(":", 1)
            if k in ("Dirty", "Writeback", "Cached", "Shmem", "MemAvailable"):
                out[k] = int(v.split()[0]) / 1024.0  # MB
    return out


def _cpu_mhz() -> dict:
    """Core clocks from /proc/cpuinfo (MHz): the busy cores' boost falls as more cores work, which
    slows every worker's host steps alike (issue 44). top16: mean of the 16 fastest cores."""
    try:
        with open("/proc/cpuinfo") as f:
            mhz = sorted((float(ln.split(":")[1]) for ln in f if ln.startswith("cpu MHz")), reverse=True)
    except (OSError, ValueError, IndexError):
        return {}
    return dict(max=mhz[0], top16=sum(mhz[:16]) / len(mhz[:16]), mean=sum(mhz) / len(mhz)) if mhz else {}


THREAD_NAMES: dict[int, str] = {}  # tid -> the thread's name (/proc comm: OpenMP, Ray's, Python's)


def _threads(pid: int) -> dict[int, int]:
    """tid -> utime + stime (clock ticks); fills THREAD_NAMES."""
    out = {}
    try:
        for tid in os.listdir(f"/proc/{pid}/task"):
            try:
                with open(f"/proc/{pid}/task/{tid}/stat") as f:
                    text = f.read()
                fields = text.rsplit(")", 1)[1].split()
                out[int(tid)] = int(fields[11]) + int(fields[12])
                THREAD_NAMES[int(tid)] = text[text.find("(") + 1:text.rfind(")")]
            except (OSError, IndexError, ValueError):
                pass
    except OSError:
        pass
    return out


def _proc_times(pid: int) -> tuple[int, int]:
    """(user, system) clock ticks of the whole process: system time is the kernel's work for it
    (page faults, mmap/munmap of large buffers, futexes, file writes)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return int(fields[11]), int(fields[12])
    except (OSError, IndexError, ValueError):
        return 0, 0


def _matching(pattern: re.Pattern) -> dict[int, str]:
    out = {}
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/cmdline", "rb") as f:
                cmd = f.read().replace(b"\0", b" ").decode(errors="replace").strip()
        except OSError:
            continue
        if cmd and pattern.search(cmd) and int(d) != os.getpid():
            out[int(d)] = cmd[:120]
    return out


def _spy(out: Path, pid: int, cmd: str, dumps: int = 2) -> None:
    """``dumps`` py-spy dumps of ``pid`` (all threads, native frames), 1 s apart, into
    OUT/spy/<pid>.txt: what its busy threads run (two dumps tell a steady loop from a moment)."""
    (out / "spy").mkdir(exist_ok=True)
    texts = []
    for i in range(dumps):
        if i:
            time.sleep(1.0)
        try:
            r = subprocess.run(["py-spy", "dump", "--native", "--pid", str(pid)], capture_output=True, text=True,
                               timeout=20)
            text = r.stdout + r.stderr
        except (OSError, subprocess.SubprocessError) as e:
            text = f"py-spy failed: {e}"
        texts.append(f"# {time.time():.3f} pid {pid} (dump {i + 1}): {cmd}\n{text}")
    (out / "spy" / f"{pid}.txt").write_text("\n".join(texts))


def sample(out: Path, interval: float, stop_file: Path | None, duration: float, match: str, spy: int = 0,
           spy_match: str = "") -> None:
    out.mkdir(parents=True, exist_ok=True)
    spy = spy if shutil.which("py-spy") else 0
    hot: dict[int, int] = {}     # pid -> samples in a row with a thread >= 0.8 core
    spied: set[int] = set()
    spied_kinds: dict[str, int] = {}
    pattern = re.compile(match)
    spy_pattern = re.compile(spy_match or match)
    smi = None
    if shutil.which("nvidia-smi"):
        smi = subprocess.Popen(["nvidia-smi", "--query-gpu=index,utilization.gpu,memory.used,clocks.sm",
                                "--format=csv,noheader,nounits", f"-lms={int(interval * 1000)}"],
                               stdout=open(out / "gpu.csv", "w"), stderr=subprocess.DEVNULL)
    t_end = time.time() + duration
    prev_cpu = _cpu_total()
    prev_threads: dict[int, dict[int, int]] = {}
    prev_times: dict[int, tuple[int, int]] = {}
    prev_t: dict[int, float] = {}  # when each process was last read: loads are over the real span
    # (a sample late by seconds, the host saturated, once divided seconds of ticks by the interval)
    names: dict[int, str] = {}
    ncpu = os.cpu_count() or 1
    with open(out / "samples.jsonl", "w") as log:
        while time.time() < t_end and not (stop_file and stop_file.exists()):
            time.sleep(interval)
            now = time.time()
            tot, idle, steal = _cpu_total()
            dt_tot, dt_idle, dt_steal = tot - prev_cpu[0], idle - prev_cpu[1], steal - prev_cpu[2]
            prev_cpu = (tot, idle, steal)
            probe = min(_probe_ms() for _ in range(3))
            procs = _matching(pattern)
            names.update(procs)
            rows = {}
            for pid in procs:
                cur = _threads(pid)
                before = prev_threads.get(pid)
                prev_threads[pid] = cur
                times, times_before = _proc_times(pid), prev_times.get(pid)
                prev_times[pid] = times
                span, prev_t[pid] = now - prev_t.get(pid, now), now
                if before is None or span <= 0:
                    continue
                d = {tid: (cur[tid] - before.get(tid, cur[tid])) / HZ / span for tid in cur}
                sys_cores = (times[1] - times_before[1]) / HZ / span if times_before else 0.0
                rows[str(pid)] = dict(cmd=procs[pid], cores=sum(d.values()), sys=sys_cores, span=round(span, 3), threads=len(cur),
                                      busy02=sum(v > 0.2 for v in d.values()), busy08=sum(v > 0.8 for v in d.values()),
                                      main=d.get(pid, 0.0), top=sorted(d.values(), reverse=True)[:6],
                                      top_named=[[THREAD_NAMES.get(t, "?"), round(v, 3)] for t, v in
                                                 sorted(d.items(), key=lambda kv: -kv[1])[:8]])
                hot[pid] = hot.get(pid, 0) + 1 if max(d.values(), default=0.0) >= 0.8 else 0
                key = procs[pid][:24]  # up to N processes of each kind (Ray workers, plain runs...)
                if (spy and hot[pid] >= 6 and pid not in spied and spied_kinds.get(key, 0) < spy
                        and spy_pattern.search(procs[pid])):
                    spied.add(pid)
                    spied_kinds[key] = spied_kinds.get(key, 0) + 1
                    # beside the sampling (a dump takes seconds: inline, it stalled the samples)
                    threading.Thread(target=_spy, args=(out, pid, procs[pid]), daemon=True).start()
            try:
                load = os.getloadavg()[0]
            except OSError:
                load = None
            log.write(json.dumps(dict(t=now, host_busy=1.0 - dt_idle / max(dt_tot, 1), cores=ncpu,
                                      steal=dt_steal / max(dt_tot, 1), probe_ms=probe, load=load,
                                      mem=_meminfo(), mhz=_cpu_mhz(), procs=rows)) + "\n")
            log.flush()
    if smi is not None:
        smi.terminate()


def summarise(out: Path, windows: list[dict]) -> list[dict]:
    samples = [json.loads(line) for line in open(out / "samples.jsonl")]
    gpu = []
    if (out / "gpu.csv").exists():
        # nvidia-smi prints one line per GPU per period, without a timestamp: spread them over the
        # samples' span in order (periods are equal)
        lines = [ln.split(",") for ln in open(out / "gpu.csv") if ln.count(",") in (2, 3)]
        gpu = [(int(v[0]), float(v[1]), float(v[2]), float(v[3]) if len(v) > 3 else float("nan"))
               for v in lines if all(x.strip().replace(".", "", 1).isdigit() for x in v)]
    res = []
    t_first = samples[0]["t"] if samples else 0.0
    t_last = samples[-1]["t"] if samples else 0.0
    n_gpu = len({g[0] for g in gpu}) or 1
    periods = len(gpu) // n_gpu
    for w in windows:
        ss = [s for s in samples if w["t0"] <= s["t"] <= w["t1"]]
        if not ss:
            continue
        row = dict(name=w["name"], seconds=w["t1"] - w["t0"], samples=len(ss),
                   host_busy=sum(s["host_busy"] for s in ss) / len(ss), cores=ss[0]["cores"],
                   load_max=max((s["load"] or 0) for s in ss),
                   dirty_mb_max=max(s["mem"].get("Dirty", 0) for s in ss),
                   writeback_mb_max=max(s["mem"].get("Writeback", 0) for s in ss))
        probes = sorted(s["probe_ms"] for s in ss if "probe_ms" in s)
        if probes:  # the median: a core's speed in this row (compare rows: same workload)
            row["probe_ms"] = round(probes[len(probes) // 2], 3)
            row["steal"] = round(sum(s.get("steal", 0.0) for s in ss) / len(ss), 4)
        mhz = [s["mhz"] for s in ss if s.get("mhz")]
        if mhz:
            row["cpu_mhz"] = {k: round(sum(m[k] for m in mhz) / len(mhz)) for k in ("max", "top16", "mean")}
        procs: dict[str, list] = {}
        for s in ss:
            for pid, p in s["procs"].items():
                procs.setdefault(pid, []).append(p)
        prow = []
        for pid, ps in procs.items():
            span = sum(p.get("span", 1.0) for p in ps)  # each sample weighs its own span
            cores = sum(p["cores"] * p.get("span", 1.0) for p in ps) / span
            if cores < 0.05:
                continue
            prow.append(dict(pid=pid, cmd=ps[0]["cmd"][:60], cores=round(cores, 2),
                             sys=round(sum(p.get("sys", 0.0) * p.get("span", 1.0) for p in ps) / span, 2),
                             threads=max(p["threads"] for p in ps),
                             busy02=round(sum(p["busy02"] for p in ps) / len(ps), 1),
                             busy08=round(sum(p["busy08"] for p in ps) / len(ps), 1),
                             main=round(sum(p["main"] for p in ps) / len(ps), 2)))
        row["procs"] = sorted(prow, key=lambda r: -r["cores"])
        if gpu and periods and t_last > t_first:
            per = (t_last - t_first) / periods
            k0 = max(0, int((w["t0"] - t_first) / per))
            k1 = min(periods, int((w["t1"] - t_first) / per) + 1)
            util: dict[int, list] = {}
            clock: dict[int, list] = {}
            for k in range(k0, k1):
                for g in gpu[k * n_gpu:(k + 1) * n_gpu]:
                    util.setdefault(g[0], []).append(g[1])
                    clock.setdefault(g[0], []).append(g[3])
            row["gpu_util"] = {i: round(sum(v) / len(v), 1) for i, v in sorted(util.items()) if v}
            row["gpu_sm_mhz"] = {i: round(sum(v) / len(v)) for i, v in sorted(clock.items()) if v and v[0] == v[0]}
        res.append(row)
    (out / "summary.json").write_text(json.dumps(res, indent=1) + "\n")
    for r in res:
        print(f"\n== {r['name']}: {r['seconds']:.1f} s, host busy {100 * r['host_busy']:.0f} % of {r['cores']} cores, "
              f"load max {r['load_max']:.0f}, dirty max {r['dirty_mb_max']:.0f} MB, writeback max "
              f"{r['writeback_mb_max']:.0f} MB, GPU util {r.get('gpu_util')}, GPU SM MHz {r.get('gpu_sm_mhz')}, "
              f"CPU MHz {r.get('cpu_mhz')}, probe {r.get('probe_ms')} ms, steal {r.get('steal')}")
        for p in r["procs"][:12]:
            print(f"   {p['pid']:>7} {p['cores']:6.2f} cores ({p['sys']:.2f} system)  {p['threads']:4d} threads  {p['busy02']:5.1f} >0.2  "
                  f"{p['busy08']:5.1f} >0.8  main {p['main']:.2f}  {p['cmd']}")
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path)
    ap.add_argument("--interval", type=float, default=0.5)
    ap.add_argument("--stop-file", type=Path)
    ap.add_argument("--duration", type=float, default=3600.0)
    ap.add_argument("--match", default=DEFAULT_MATCH)
    ap.add_argument("--spy", type=int, default=0, metavar="N", help="py-spy dumps of up to N busy processes of each kind")
    ap.add_argument("--spy-match", default="", help="regex: only these processes are dumped (default: --match)")
    ap.add_argument("--summarise", type=Path, help="summarise an earlier sampling folder")
    ap.add_argument("--windows", type=Path, help="JSON list of {name, t0, t1}")
    args = ap.parse_args()
    if args.summarise:
        windows = json.loads(args.windows.read_text()) if args.windows else []
        if windows and isinstance(windows, dict):  # a bench JSON with rows holding t0/t1
            windows = [dict(name=r["mode"], t0=r["t0"], t1=r["t1"]) for r in windows.get("rows", []) if "t0" in r]
        summarise(args.summarise, windows)
    else:
        sample(args.out, args.interval, args.stop_file, args.duration, args.match, args.spy, args.spy_match)


if __name__ == "__main__":
    main()
