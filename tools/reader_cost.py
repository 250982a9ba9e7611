"""What one frame costs on the host in ``floxels run``'s reader path, per layout and per function
(issue 42): wall, CPU and GIL-held ms a frame of ``load_frame`` (read, checks, crop + ground,
row selection, checksum) and the functions under it, run on this thread over a bench_run
sequence (``bench/bench_run.py``'s ``build``: KITTI ``.bin`` files + ``poses.txt`` and an
Argoverse 2 log of ``.feather`` sweeps, the same frames).

    python tools/reader_cost.py --seq /tmp/seq120 --frames 120 --repeat 3   # builds it if absent
    python tools/reader_cost.py --seq /tmp/seq120 --repo ../other-checkout    # another commit's code

Two passes a repetition, the layouts interleaved (kitti, av2, kitti, av2, ...):

* wall and CPU: each part's wall time and this thread's CPU time (``time.thread_time``) around
  it, and the process's CPU (``getrusage``: also the threads a library starts, e.g. pyarrow's);
* GIL: a helper thread loops in pure Python while the frames are read, clocking each turn; a
  part holds the GIL for the gaps in those turns during it (a turn more than 5 us after the
  last). The helper needs the second core: on a loaded host its gaps also count the core taken
  from it, so compare rows of one run (``--repeat``: the median is shown). With the helper
  waiting, Python hands the GIL over every 0.5 ms (floxels run's switch interval): a part's wall
  then includes its waits for the GIL back, as beside the optimiser's thread in a run.

Nested parts are indented under the part that calls them (their time is in their parent's).

``--cold N``: also the first sequence of a fresh engine process, N times a layout: a new
interpreter that imports what the fork server preloads for its engines
(``pipeline/worker_processes._PRELOAD``), then times opening the sequence (``discover_input``:
files, poses) and reading its first frame (``load_frame``), and says which of pyarrow and pandas
that imported.

Measurement only: nothing here ships.
"""

from __future__ import annotations

import argparse
import functools
import importlib
import json
import resource
import statistics
import sys
import threading
import time
from pathlib import Path

# (module, attribute, part name): where a caller imports a function by name, that module's name
# is patched (frame_loader imports far_outliers at module level, the rest at call time)
_PARTS = [
    ("floxels_ext.lidar.pipeline.frame_loader", "load_frame", "load_frame (all of it)"),
    ("floxels_ext.lidar.io.sources", "read_points", "  read_points"),
    ("floxels_ext.lidar.io.readers", "read_bin", "    read_bin"),
    ("floxels_ext.lidar.io.readers", "_read_float32", "      file read"),
    ("floxels_ext.lidar.io.readers", "_check_bin_plausible", "      .bin checks"),
    ("floxels_ext.lidar.io.readers", "_ordered_columns", "        scan-order test"),
    ("floxels_ext.lidar.io.readers", "read_feather", "    read_feather"),
    ("pyarrow.feather", "read_table", "      feather.read_table"),
    ("floxels_ext.lidar.io.readers", "_finish", "      _finish"),
    ("floxels_ext.lidar.pipeline.frame_checks", "float32_far_message", "  float32_far_message"),
    ("floxels_ext.lidar.preprocess.masks", "preprocess_classes", "  crop + ground (preprocess_classes)"),
    ("floxels_ext.ops.lidar", "lidar_select", "  lidar_select"),
    ("floxels_ext.lidar.pipeline.frame_loader", "far_outliers", "  far_outliers"),
    ("floxels_ext.lidar.io.outputs", "points_crc32", "  points_crc32"),
]


class Counter:
    """A thread looping in pure Python, clocking each turn: a turn that came more than 5 us after
    the previous one means the GIL was held elsewhere (or the core taken) meanwhile. ``held()``:
    the nanoseconds of such gaps so far, the current one included (the caller holds the GIL)."""

    GAP_NS = 5000

    def __init__(self) -> None:
        self.s = [time.perf_counter_ns(), 0]  # last turn, gaps so far
        self.stop = False
        self.th = threading.Thread(target=self._spin, daemon=True)
        self.th.start()

    def _spin(self) -> None:
        s, clock, gap_ns = self.s, time.perf_counter_ns, self.GAP_NS
        while not self.stop:
            t = clock()
            if t - s[0] > gap_ns:
                s[1] += t - s[0]
            s[0] = t

    def held(self) -> int:
        t = time.perf_counter_ns()
        last, gaps = self.s
        return gaps + (t - last if t - last > self.GAP_NS else 0)

    def close(self) -> None:
        self.stop = True
        self.th.join()


class Parts:
    def __init__(self) -> None:
        self.counter: Counter | None = None
        self.reset()
        for mod, attr, name in _PARTS:
            owner = importlib.import_module(mod)
            if not hasattr(owner, attr):
                continue  # an older checkout without that function
            orig = getattr(owner, attr)
            wrapped = functools.wraps(orig)(functools.partial(self._timed, orig, name))
            setattr(owner, attr, wrapped)
            readers = importlib.import_module("floxels_ext.lidar.io.readers")
            for k, v in list(readers.READERS.items()):  # read_points dispatches through this dict
                if v is orig:
                    readers.READERS[k] = wrapped

    def reset(self) -> None:
        self.acc = {name: [0, 0, 0] for _, _, name in _PARTS}  # wall, thread CPU, GIL held elsewhere (ns)

    def _timed(self, orig, name, *a, **kw):
        c = self.counter
        n0, w0, t0 = (c.held() if c else 0), time.perf_counter_ns(), time.thread_time_ns()
        try:
            return orig(*a, **kw)
        finally:
            acc = self.acc[name]
            acc[0] += time.perf_counter_ns() - w0
            acc[1] += time.thread_time_ns() - t0
            acc[2] += (c.held() - n0) if c else 0


def read_all(seq, frames: int, settings, keep_ground: bool) -> None:
    from floxels_ext.lidar.pipeline.frame_loader import load_frame

    for i in range(frames):
        res = load_frame(i, seq, settings, "table", seq.poses, False, keep_ground=keep_ground)
        if "frame" not in res:
            sys.exit(f"frame {i}: {res.get('error')}")


_COLD = """
import sys, time
from pathlib import Path
from floxels_ext.lidar.pipeline.worker_processes import _PRELOAD
for m in _PRELOAD:
    __import__(m)
from floxels_ext.lidar.io.sources import discover_input
from floxels_ext.lidar.pipeline.frame_loader import load_frame
from floxels_ext.lidar.preprocess import Preprocess
seq, lay = Path(sys.argv[1]), sys.argv[2]
before = {m for m in ("pyarrow", "pandas") if m in sys.modules}
t0 = time.perf_counter()
s = (discover_input(seq / "kitti" / "velodyne", poses_file=seq / "kitti" / "poses.txt") if lay == "kitti"
     else discover_input(seq / "av2"))
t1 = time.perf_counter()
res = load_frame(0, s, Preprocess(), "table", s.poses, False)
t2 = time.perf_counter()
assert "frame" in res, res
new = sorted(m for m in ("pyarrow", "pandas") if m in sys.modules and m not in before)
print(1e3 * (t1 - t0), 1e3 * (t2 - t1), ",".join(new) or "-")
"""


def cold(repo: Path, seq: Path, layouts, times: int) -> dict:
    """ms to open the sequence and read its first frame in a fresh engine-like process."""
    import os
    import subprocess

    py = str(repo / "python" if (repo / "python").is_dir() else repo)
    env = dict(os.environ, PYTHONPATH=py)
    out: dict = {k: [] for k in layouts}
    for _ in range(times):
        for k in layouts:
            r = subprocess.run([sys.executable, "-c", _COLD, str(seq), k], capture_output=True, text=True, env=env)
            if r.returncode:
                sys.exit(r.stderr)
            a, b, mods = r.stdout.split()
            out[k].append((float(a), float(b), mods))
    print(f"\nfirst sequence of a fresh engine process ({times} processes a layout; ms)")
    for k in layouts:
        rows = out[k]
        print(f"  {k}: open {statistics.median(r[0] for r in rows):7.1f}, first frame "
              f"{statistics.median(r[1] for r in rows):7.1f}, imported: {rows[0][2]} (runs: "
              + ", ".join(f"{r[0]:.0f}+{r[1]:.0f}" for r in rows) + ")")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repo", default=str(Path(__file__).resolve().parents[1]),
                    help="checkout whose python/ package runs (default: this one)")
    ap.add_argument("--seq", type=Path, required=True, help="a bench_run sequence root; made if absent")
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--beams", type=int, default=128)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--layout", nargs="+", default=["kitti", "av2"], choices=["kitti", "av2"])
    ap.add_argument("--keep-ground", action="store_true", help="as for a method that reads the ground")
    ap.add_argument("--cold", type=int, default=0, metavar="N",
                    help="also time a fresh engine process's first sequence, N processes a layout")
    ap.add_argument("--json", type=Path, help="also write the medians here")
    args = ap.parse_args()
    repo = Path(args.repo).resolve()
    sys.path.insert(0, str(repo / "python" if (repo / "python").is_dir() else repo))
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
    from floxels_ext.lidar.io.sources import discover_input
    from floxels_ext.lidar.preprocess import Preprocess

    if not (args.seq / "kitti" / "poses.txt").exists():
        from bench_run import build

        build(args.seq, args.frames, args.beams, 1800, 0)
    seqs = {"kitti": discover_input(args.seq / "kitti" / "velodyne", poses_file=args.seq / "kitti" / "poses.txt"),
            "av2": discover_input(args.seq / "av2")}
    frames = min([args.frames] + [len(seqs[k]) for k in args.layout])
    sys.setswitchinterval(0.0005)  # as floxels run sets it
    parts, settings = Parts(), Preprocess()
    runs: dict = {k: [] for k in args.layout}
    for k in args.layout:  # warm-up: imports, the op's first call, the page cache
        read_all(seqs[k], min(4, frames), settings, args.keep_ground)
    for _ in range(args.repeat):
        for k in args.layout:
            parts.counter = None
            parts.reset()
            r0 = resource.getrusage(resource.RUSAGE_SELF)
            read_all(seqs[k], frames, settings, args.keep_ground)
            r1 = resource.getrusage(resource.RUSAGE_SELF)
            clean = {name: v[:2] for name, v in parts.acc.items()}
            proc = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
            counter = parts.counter = Counter()
            parts.reset()
            read_all(seqs[k], frames, settings, args.keep_ground)
            counter.close()
            parts.counter = None
            gil = {name: v[2] for name, v in parts.acc.items()}
            runs[k].append({name: [clean[name][0] / 1e6 / frames, clean[name][1] / 1e6 / frames,
                                   gil[name] / 1e6 / frames] for name in clean} | {"process CPU": 1e3 * proc / frames})
    print(f"{repo}: {frames} frames a layout, {args.repeat} repetitions (median); ms a frame")
    out = {}
    for k in args.layout:
        med = {name: [statistics.median(r[name][j] for r in runs[k]) for j in range(3)] for _, _, name in _PARTS}
        proc = statistics.median(r["process CPU"] for r in runs[k])
        out[k] = {"parts": med, "process_cpu_ms": proc}
        print(f"\n{k}: process CPU {proc:.2f} ms a frame (runs: "
              + ", ".join(f"{r['process CPU']:.2f}" for r in runs[k]) + ")")
        print(f"  {'part':<40} {'wall':>7} {'CPU':>7} {'GIL':>7}")
        for _, _, name in _PARTS:
            w, c, g = med[name]
            if w > 0:
                print(f"  {name:<40} {w:7.2f} {c:7.2f} {g:7.2f}")
    if args.cold:
        out["cold"] = cold(repo, args.seq, args.layout, args.cold)
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
