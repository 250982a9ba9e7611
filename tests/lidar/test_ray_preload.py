"""A Ray cluster started with ``ray_preload.RAY_ENV`` (Ray's worker prestart and module preload)
gives ``floxels run --ray`` fresh workers whose ``import torch`` and compiled ops were loaded
before the job asked for them (issue 44: workers that start fast). The check is on the worker's
own stamps in ``OUT/ray_job_summary.json``: its process holds the preloaded module, and its
``__init__`` found torch already imported."""

import json
import os
import sys
import time

import pytest

ray = pytest.importorskip("ray")
cluster_utils = pytest.importorskip("ray.cluster_utils")

from floxels_ext import cli  # noqa: E402
from floxels_ext.evaluation.seqio import save_sequence  # noqa: E402
from floxels_ext.evaluation.sim import simulate_sequence  # noqa: E402
from floxels_ext.lidar.dataset import ray_preload  # noqa: E402
from ray_procs import cmdline, process_tree  # noqa: E402

FLAGS = ["--device", "cpu", "--max-iters", "3", "--scans", "3"]


def test_preload_module_names_itself_and_leaves_cuda_alone():
    assert ray_preload.RAY_ENV == {"RAY_enable_worker_prestart": "1",
                                   "RAY_preload_python_modules": "floxels_ext.lidar.dataset.ray_preload"}
    assert "torch" in sys.modules and "floxels_ext.lidar.dataset.ray_worker" in sys.modules
    import torch

    # a prestarted process does not know its GPU yet: the preload must not create a CUDA context
    assert not torch.cuda.is_initialized()


def test_worker_seeing_more_gpus_than_ray_gave_it_is_reported(capsys):
    from floxels_ext.lidar.dataset.ray_report import format_timeline, report_workers

    base = {"name": "w", "host": "h", "pid": 1, "claimed": False, "written": 3, "gpus": ["1"],
            "timeline": {"preloaded": -9.0, "requested": 0.1, "first_output": 1.5}}
    report_workers([base | {"cuda_devices": 1}, base | {"gpus": [], "cuda_devices": 4}], verbosity=0)
    assert capsys.readouterr().err == ""
    report_workers([base | {"cuda_devices": 2}], verbosity=0)
    err = capsys.readouterr().err
    assert "floxels: warning: w sees 2 GPUs though Ray gave it 1" in err, err
    assert format_timeline(base["timeline"]) == "preloaded (torch, ops) -9.00, requested +0.10, first output +1.50"


def _preloaded_idle_workers(raylet: int) -> list[int]:
    """The raylet's idle Python workers that finished the preload (they mapped the compiled ops)."""
    done = []
    for pid in process_tree(raylet)[1:]:
        if "default_worker" not in cmdline(pid) and "ray::IDLE" not in cmdline(pid):
            continue
        try:
            with open(f"/proc/{pid}/maps") as f:
                if "floxels_ext/_C" in f.read():
                    done.append(pid)
        except OSError:
            pass
    return done


@pytest.mark.slow
@pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="finds the node's processes in /proc")
def test_fresh_worker_takes_a_preloaded_process(tmp_path, capsys):
    if ray.is_initialized():
        ray.shutdown()
    saved = {k: os.environ.get(k) for k in ray_preload.RAY_ENV}
    os.environ.update(ray_preload.RAY_ENV)  # read by the raylet when it starts, as `ray start` would
    try:
        c = cluster_utils.Cluster(initialize_head=True, head_node_args={
            "num_cpus": 1, "include_dashboard": False, "object_store_memory": 100 * 1024 * 1024})
    finally:
        for k, v in saved.items():
            os.environ.pop(k, None) if v is None else os.environ.__setitem__(k, v)
    try:
        ray.init(address=c.address, log_to_driver=False)
        raylet = c.head_node.all_processes["raylet"][0].process.pid
        deadline = time.monotonic() + 90
        while not _preloaded_idle_workers(raylet) and time.monotonic() < deadline:
            time.sleep(0.5)
        assert _preloaded_idle_workers(raylet), "Ray prestarted no worker with the preload"
        root = tmp_path / "ds"
        save_sequence(root / "s0", simulate_sequence("urban", 4, 0, beams=16, azimuth_steps=360))
        out = tmp_path / "ray"
        rc = cli.main(["run", str(root), "--out", str(out), "--ray", "--cpus-per-task", "1", "--keep-workers", "0",
                       "--retries", "0", "-v", *FLAGS])
        err = capsys.readouterr().err
        assert rc == 0, err
        (w,) = json.loads((out / "ray_job_summary.json").read_text())["workers"]
        tl = w["timeline"]
        assert not w["claimed"]  # started for this job, not a pooled worker
        assert "preloaded" in tl, tl
        assert tl["process"] < 0 and tl["preloaded"] < 0, tl  # the process and its imports came before the job
        assert tl["torch"] - tl["init"] < 0.5, tl  # __init__ found torch and the ops loaded
        assert "preloaded (torch, ops)" in err, err
    finally:
        ray.shutdown()
        c.shutdown()
