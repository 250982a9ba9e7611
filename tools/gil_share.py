"""How long each of ``floxels run``'s per-frame host steps holds the GIL (issue 16): the time a
pure-Python loop on the main thread loses while one helper thread repeats the step, per call
(the control, a GIL-free op, shows what the cores' own contention costs on this host).
The optimiser's thread is mostly Python launching kernels, so this is about what each frame's
reader or writer work takes from it.

    python tools/gil_share.py [--seconds 3]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from bench_run import build  # noqa: E402

from floxels_ext.lidar.pipeline.frame_loader import load_frame  # noqa: E402
from floxels_ext.lidar.pipeline.frame_writer import FrameOutput  # noqa: E402
from floxels_ext.lidar.io import read_points  # noqa: E402
from floxels_ext.lidar.preprocess import Preprocess, preprocess_mask  # noqa: E402


def python_rate(seconds: float) -> float:
    """Iterations a second of a pure-Python loop on this thread."""
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        for _ in range(1000):
            n += 1
    return n / (time.perf_counter() - t0)


def gil_per_call(step, seconds: float, alone: float) -> tuple[float, float]:
    stop, calls = threading.Event(), [0]

    def loop():
        while not stop.is_set():
            step()
            calls[0] += 1

    th = threading.Thread(target=loop, daemon=True)
    th.start()
    rate = python_rate(seconds)
    stop.set()
    th.join()
    lost = max(0.0, 1 - rate / alone) * seconds
    return 1e3 * lost / max(calls[0], 1), 1e3 * seconds / max(calls[0], 1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--beams", type=int, default=128)
    a = ap.parse_args()
    sys.setswitchinterval(0.0005)  # as floxels run sets it
    with tempfile.TemporaryDirectory() as tmp:
        kitti, av2, _ = build(Path(tmp), 2, a.beams, 1800, 0)
        bins = sorted((kitti / "velodyne").glob("*.bin"))
        feathers = sorted((av2 / "sensors" / "lidar").glob("*.feather"))

        class Seq:
            def __init__(self, files):
                self.frames = [type("F", (), {"path": f, "name": f.stem}) for f in files]

            def load(self, i):
                return read_points(self.frames[i].path)

        kseq, aseq = Seq(bins), Seq(feathers)
        fr = load_frame(0, kseq, Preprocess(), "identity", None, False)["frame"]
        out = Path(tmp) / "out"
        out.mkdir()
        writer = FrameOutput({0: out / "000000.npz"}, {0: str(bins[0])}, [None],
                             {"method": np.str_("floxels"), "num_scans": np.int64(5),
                              "options": np.str_("{}"), "settings": np.str_('{"min_range": 3.0}')}, 0.05)
        flow = np.zeros((len(fr.kept), 3), np.float32)
        pts = read_points(bins[0]).points
        steps = {
            "control: the keep-mask op alone (no GIL)": lambda: preprocess_mask(pts),
            "read + preprocess a .bin (load_frame)": lambda: load_frame(0, kseq, Preprocess(), "identity", None, False),
            "read + preprocess a .feather": lambda: load_frame(0, aseq, Preprocess(), "identity", None, False),
            "write an output (FrameOutput)": lambda: writer(0, fr, flow, 0.01, np.eye(4)),
        }
        alone = python_rate(a.seconds)
        print(f"GIL held per call (ms), {a.beams}-beam frame of {fr.n} points; switch interval 0.5 ms")
        for name, step in steps.items():  # median of 3 (the main loop's own rate drifts)
            runs = sorted(gil_per_call(step, a.seconds, alone) for _ in range(3))
            held, wall = runs[1]
            print(f"  {name:40s} {held:6.2f} of {wall:6.2f} ms a call (runs: "
                  + ", ".join(f"{h:.2f}" for h, _ in runs) + ")")


if __name__ == "__main__":
    main()
