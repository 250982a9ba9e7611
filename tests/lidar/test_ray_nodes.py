"""``floxels run DATASET --ray`` on a Ray cluster of two nodes on this machine (a head and a second
node, 1 CPU each, so one worker runs on each), and the second node lost mid-run: its worker
processes killed (as by a power cut) and the node removed. Nothing is lost (every frame is
written by the end, equal to the local run's) and nothing is written twice (each output present
at the kill keeps its inode and mtime; no output is replaced while the job goes on)."""

import os
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest

ray = pytest.importorskip("ray")
cluster_utils = pytest.importorskip("ray.cluster_utils")

from floxels_ext import cli  # noqa: E402
from floxels_ext.evaluation.seqio import save_sequence  # noqa: E402
from floxels_ext.evaluation.sim import simulate_sequence  # noqa: E402
from floxels_ext.lidar.io.outputs import read_flow_output  # noqa: E402
from ray_procs import cmdline, output_stamps, process_tree, run_beside  # noqa: E402

pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="finds the node's processes in /proc")]

FLAGS = ["--device", "cpu", "--max-iters", "3", "--scans", "3", "--chunk", "1"]
RAY = ["--ray", "--task-frames", "2", "--cpus-per-task", "1", "--keep-workers", "0", "--retries", "0"]
N_SEQ, N_FRAMES = 2, 6


@pytest.fixture(scope="module")
def two_nodes():
    if ray.is_initialized():
        ray.shutdown()
    # a lost node is noticed after 2 missed health checks of 0.5 s (Ray's default waits ~15-30 s)
    fast = {"health_check_period_ms": 500, "health_check_failure_threshold": 2, "health_check_initial_delay_ms": 0}
    store = 100 * 1024 * 1024
    c = cluster_utils.Cluster(initialize_head=True, head_node_args={
        "num_cpus": 1, "include_dashboard": False, "object_store_memory": store, "_system_config": fast})
    second = c.add_node(num_cpus=1, object_store_memory=store)
    ray.init(address=c.address, log_to_driver=False)
    c.wait_for_nodes()
    yield c, second
    ray.shutdown()
    c.shutdown()


class _NodeKiller(threading.Thread):
    """Once ``out`` holds 2 frames and the second node runs a worker, SIGKILLs every process of
    that node's raylet tree (its workers first, so none writes after the snapshot), records each
    output present then, and removes the node; watches every output for one replaced later."""

    def __init__(self, cluster, node, out: Path):
        super().__init__(daemon=True)
        self.cluster, self.node, self.out = cluster, node, out
        self.raylet = node.all_processes["raylet"][0].process.pid
        self.at_kill: dict | None = None
        self.inodes: dict = {}
        self.rewritten: list = []
        self.stop = False
        self.error = None

    def run(self):
        try:
            while not self.stop:
                for p, (ino, _) in output_stamps(self.out).items():
                    if self.inodes.setdefault(p, ino) != ino:
                        self.rewritten.append(p)
                if self.at_kill is None and len(self.inodes) >= 2:
                    workers = [p for p in process_tree(self.raylet) if cmdline(p).startswith("ray::FloxelsWorker")]
                    if workers:
                        for p in reversed(process_tree(self.raylet)):  # children before their parents
                            if p != self.raylet:
                                os.kill(p, signal.SIGKILL)
                        os.kill(self.raylet, signal.SIGKILL)
                        self.at_kill = output_stamps(self.out)
                        self.cluster.remove_node(self.node, allow_graceful=False)
                time.sleep(0.02)
        except BaseException as e:  # noqa: BLE001 - reported by the test
            self.error = e


def test_second_node_lost_mid_run(two_nodes, tmp_path, capsys):
    cluster, second = two_nodes
    assert len([n for n in ray.nodes() if n["Alive"]]) == 2
    root = tmp_path / "ds"
    for k, scene in enumerate(("urban", "crossing")[:N_SEQ]):
        save_sequence(root / f"s{k}", simulate_sequence(scene, N_FRAMES, k, beams=16, azimuth_steps=360))
    local = tmp_path / "local"
    assert cli.main(["run", str(root), "--out", str(local), *FLAGS]) == 0
    out = tmp_path / "ray"
    cmd = ["run", str(root), "--out", str(out), *RAY, *FLAGS]
    killer = _NodeKiller(cluster, second, out)
    rc, err = run_beside(killer, cmd, capsys)
    print(err)  # shown with pytest -rP
    assert killer.error is None, killer.error
    assert killer.at_kill is not None, "the second node was not killed mid-run:\n" + err
    assert len(killer.at_kill) < N_SEQ * N_FRAMES, "killed too late: every frame was written already"
    assert "2 worker(s) of 0 GPU + 1 CPU" in err and "1 worker(s) lost" in err, err
    if rc != 0:  # as documented: the same command again writes what is missing
        assert "no worker left" in err, err
        rc = cli.main(cmd)
        err += capsys.readouterr().err
    assert rc == 0, err
    assert not killer.rewritten, f"written twice: {killer.rewritten}"
    after = output_stamps(out)
    assert {p: after[p] for p in killer.at_kill} == killer.at_kill, "an output present at the kill was rewritten"
    names = sorted(p.relative_to(out).as_posix() for p in after)
    assert names == sorted(p.relative_to(local).as_posix() for p in local.rglob("*.npz"))
    assert len(names) == N_SEQ * N_FRAMES
    for rel in names:
        a, b = read_flow_output(out / rel), read_flow_output(local / rel)
        assert np.array_equal(a["mask"], b["mask"]), rel
        np.testing.assert_allclose(a["flow"], b["flow"], rtol=0, atol=1e-5, err_msg=rel)
    assert not list(out.rglob(".*.tmp")), "temporary files left"
