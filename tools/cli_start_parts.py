"""Where a fresh ``floxels run`` spends the seconds before its first task (issue 42: a fresh
768-frame run spent ~3.6 s there, bench/RESULTS.md D2): each part timed in a fresh process of
its own, the median of ``--repeat``. Parts: Python's start; ``import torch``; the package's
engine imports (the fork server's preload); a CUDA context, plain; a private MPS daemon's start
and test (``mps.start_private_mps``, the daemon stopped after each); a CUDA context as a client
of a daemon started beforehand.

    python tools/cli_start_parts.py [--repeat 3] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

PARTS = {
    "python start": "pass",
    "import torch": "import torch",
    "the engine's imports (fork server preload)": (
        "from floxels_ext.lidar.pipeline.worker_processes import _PRELOAD\n"
        "import importlib\nfor m in _PRELOAD: importlib.import_module(m)"),
    "import torch + CUDA context": "import torch; torch.zeros(1, device='cuda'); torch.cuda.synchronize()",
    "private MPS daemon: start and test": (
        "import time\nfrom floxels_ext.lidar.dataset import mps\nt = time.perf_counter()\n"
        "mps.start_private_mps()\nprint('INNER', time.perf_counter() - t)"),  # (its watcher stops it)
}


def timed(code: str, env: dict | None = None) -> tuple[float, float | None, int]:
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    inner = next((float(x.split()[1]) for x in p.stdout.splitlines() if x.startswith("INNER")), None)
    if p.returncode != 0:
        print(p.stderr[-600:], file=sys.stderr)
    return wall, inner, p.returncode


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    rows: dict[str, list] = {}
    for _ in range(args.repeat):
        for name, code in PARTS.items():
            rows.setdefault(name, []).append(timed(code))
            if "MPS" in name:
                time.sleep(2.5)  # the private daemon's watcher stops it ~1 s after its process
        # a CUDA context through a daemon already running (the engines' case)
        control = shutil.which("nvidia-cuda-mps-control")
        if control:
            d = tempfile.mkdtemp(prefix="cli_start_mps_")
            env = dict(os.environ, CUDA_MPS_PIPE_DIRECTORY=d, CUDA_MPS_LOG_DIRECTORY=d)
            subprocess.run([control, "-d"], env=env)
            rows.setdefault("import torch + CUDA context, MPS client (server's first client)", []).append(
                timed(PARTS["import torch + CUDA context"], env))
            rows.setdefault("import torch + CUDA context, MPS client (server up)", []).append(
                timed(PARTS["import torch + CUDA context"], env))
            subprocess.run([control], input="quit\n", text=True, env=env, capture_output=True)
            time.sleep(1.0)
            shutil.rmtree(d, ignore_errors=True)
    out = {}
    print(f"{'part (a fresh process each)':<66}{'wall s':>8}{'inside s':>10}  rc")
    for name, vals in rows.items():
        wall = statistics.median(v[0] for v in vals)
        inner = [v[1] for v in vals if v[1] is not None]
        out[name] = {"wall_s": wall, "inner_s": statistics.median(inner) if inner else None,
                     "runs": [list(v) for v in vals]}
        print(f"{name:<66}{wall:>8.2f}{(out[name]['inner_s'] or float('nan')):>10.2f}  "
              f"{','.join(str(v[2]) for v in vals)}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
