"""A Ray job's driver lists and plans the dataset and hands out its first tasks without importing
torch (~1-2 s on a GPU host, before a warm pool's first frame): it needed it only to learn the
preset's window (``floxels_ext.presets``)."""

import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np

PROBE = textwrap.dedent("""
    import contextlib, sys
    from floxels_ext import cli
    from floxels_ext.lidar.dataset import ray_runner

    @contextlib.contextmanager
    def early(args):  # the cluster's part: not under test here
        yield object()

    seen = {}

    def first_tasks(tasks, args, common, n_sequences, workers, align=0):
        seen["torch"] = "torch" in sys.modules
        seen["tasks"] = len(tasks)
        return 0

    ray_runner.early_workers, ray_runner.run_on_ray = early, first_tasks
    rc = cli.main(["run", sys.argv[1], "--out", sys.argv[2], "--ray", "--preset", "accurate", "-q"])
    print(rc, seen["tasks"], seen["torch"])
""")


def test_driver_plans_without_torch(tmp_path):
    for k in range(2):
        d = tmp_path / "data" / "sequences" / f"{k:02d}" / "velodyne"
        d.mkdir(parents=True)
        for i in range(3):
            np.zeros((4, 4), np.float32).tofile(d / f"{i:06d}.bin")
        poses = tmp_path / "data" / "poses"
        poses.mkdir(exist_ok=True)
        np.savetxt(poses / f"{k:02d}.txt", np.tile(np.eye(4)[:3].reshape(1, 12), (3, 1)))
    src = Path(__file__).resolve().parents[2] / "python"
    out = subprocess.run([sys.executable, "-c", PROBE, str(tmp_path / "data"), str(tmp_path / "out")],
                         capture_output=True, text=True, env={"PYTHONPATH": str(src), "PATH": "/usr/bin:/bin"},
                         timeout=120)
    assert out.stdout.split() == ["0", "2", "False"], out.stdout + out.stderr
