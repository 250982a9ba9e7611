"""``floxels run DATASET --ray`` on a local Ray cluster (2 CPUs, loopback only): the outputs equal the
local run's; a second job reuses the warm workers of the first (the same processes, the same
outputs) and the pool empties itself after its idle timeout; a worker actor killed mid-run (by
its process id) hands its tasks to the other worker (or a replacement), or, when none is left,
the frames not written are reported by file name, and a re-run writes only what is missing
(nothing lost, nothing written twice, no temporary files left)."""

import json
import os
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

ray = pytest.importorskip("ray")

from floxels_ext import cli  # noqa: E402
from floxels_ext.lidar.io.outputs import read_flow_output  # noqa: E402
from floxels_ext.evaluation.seqio import save_sequence  # noqa: E402
from ray_procs import cmdline, output_stamps, run_beside  # noqa: E402

FLAGS = ["--device", "cpu", "--max-iters", "3", "--scans", "3", "--chunk", "1"]
N_FRAMES = 4


@pytest.fixture(scope="module")
def cluster():
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False,
             _node_ip_address="127.0.0.1")
    yield
    ray.shutdown()


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """3 small simulated sequences in two formats, listed in a text file: two `floxels simulate`
    directories and one KITTI-style sequence (sensor-frame .bin files + poses/NN.txt)."""
    from floxels_ext.lidar.preprocess import transform_points
    from floxels_ext.evaluation.sim import simulate_sequence

    root = tmp_path_factory.mktemp("ds")
    for k, scene in enumerate(("urban", "crossing")):
        save_sequence(root / "sim" / f"s{k}", simulate_sequence(scene, N_FRAMES, k, beams=16, azimuth_steps=360))
    seq = simulate_sequence("highway", N_FRAMES, 2, beams=16, azimuth_steps=360)
    velo = root / "kitti/sequences/00/velodyne"
    velo.mkdir(parents=True)
    for i, fr in enumerate(seq.frames):
        p = transform_points(fr.points, np.linalg.inv(fr.pose))
        np.c_[p, np.zeros(len(p))].astype(np.float32).tofile(velo / f"{i:06d}.bin")
    (root / "kitti/poses").mkdir()
    np.savetxt(root / "kitti/poses/00.txt", np.stack([f.pose[:3] for f in seq.frames]).reshape(-1, 12))
    lst = root / "list.txt"
    lst.write_text("sim/s0\nsim/s1\nkitti/sequences/00/velodyne\n")
    local = root / "local"
    assert cli.main(["run", str(lst), "--out", str(local), *FLAGS]) == 0
    return lst, local


def _outputs(out: Path) -> list[str]:
    return sorted(p.relative_to(out).as_posix() for p in out.rglob("*.npz"))


def _assert_same(out: Path, ref: Path):
    assert _outputs(out) == _outputs(ref) and len(_outputs(ref)) == 3 * N_FRAMES
    for rel in _outputs(ref):
        a, b = read_flow_output(out / rel), read_flow_output(ref / rel)
        assert np.array_equal(a["mask"], b["mask"]), rel
        assert np.array_equal(a["dynamic"], b["dynamic"]), rel
        assert np.array_equal(a["points"], b["points"], equal_nan=True), rel
        np.testing.assert_allclose(a["flow"], b["flow"], rtol=0, atol=1e-5, err_msg=rel)
    assert not [p for p in out.rglob(".*.tmp")], "temporary files left"


def _assert_summaries(out: Path, ref: Path):
    """Each sequence's run_summary.json counts its whole run, as the local run's does (each
    task of a sequence cut into tasks once wrote its own frames' summary over the others')."""
    keys = ("frames", "selected", "written", "skipped", "failed")
    refs = sorted(p.relative_to(ref) for p in ref.rglob("run_summary.json"))
    assert refs and refs == sorted(p.relative_to(out) for p in out.rglob("run_summary.json"))
    for rel in refs:
        a, b = (json.loads((d / rel).read_text()) for d in (out, ref))
        assert {k: a[k] for k in keys} == {k: b[k] for k in keys}, rel


def _pool() -> list[str]:
    return [a["name"] for a in ray.util.list_named_actors(all_namespaces=True) if a["namespace"] == "floxels"]


def _empty_pool(timeout: float = 20.0) -> None:
    """Idle pooled workers of earlier tests exit (the kill tests must find only their job's)."""
    for name in _pool():
        try:
            ray.get(ray.get_actor(name, namespace="floxels").retire.remote(), timeout=10)
        except (ValueError, ray.exceptions.RayError):
            pass
    t = time.time()
    while _pool() and time.time() - t < timeout:
        time.sleep(0.1)
    assert not _pool()


def test_ray_equals_local_and_warm_pool(cluster, dataset, tmp_path, capsys):
    lst, local = dataset
    _empty_pool()
    out = tmp_path / "ray"
    # tasks of 2 frames: each sequence is cut into 3 chunks that share its output directory
    cmd = ["run", str(lst), "--out", str(out), "--ray", "--task-frames", "2", "--keep-workers", "30", "-v", *FLAGS]
    assert cli.main(cmd) == 0
    err = capsys.readouterr().err
    assert "3 sequences, 12 frames, 0 already done, 12 to estimate in 6 task(s) on Ray" in err
    _assert_same(out, local)
    _assert_summaries(out, local)
    first = json.loads((out / "ray_job_summary.json").read_text())
    assert first["frames_written"] == 12 and first["tasks"]["done"] == 6
    pids = {w["pid"] for w in first["workers"]}
    assert len(pids) == 2 and not any(w["warm"] for w in first["workers"])
    for w in first["workers"]:  # the start timeline, relative to the job's start, in its order
        tl = w["timeline"]
        assert tl["init"] <= tl["run"] <= tl["first_task"] <= tl["first_output"] <= tl["last_output"] <= tl["end"]
        assert f"{w['name']} (" in err and "first output" in err
    assert len(_pool()) == 2  # they wait for the next job
    # the same job again, from scratch: the same (warm) processes take it, the outputs are the same
    out2 = tmp_path / "ray2"
    cmd[cmd.index(str(out))] = str(out2)
    assert cli.main(cmd) == 0
    assert "2 of them warm from the pool" in capsys.readouterr().err
    second = json.loads((out2 / "ray_job_summary.json").read_text())
    assert {w["pid"] for w in second["workers"]} == pids and all(w["warm"] for w in second["workers"])
    assert all(w["timeline"]["init"] < 0 for w in second["workers"])  # started before this job
    _assert_same(out2, local)
    # a job with another pool setting retires the idle workers it cannot use; without a pool the
    # workers stop with the job, and pooled ones exit after their idle timeout
    out3 = tmp_path / "ray3"
    assert cli.main(["run", str(lst), "--out", str(out3), "--ray", "--keep-workers", "0", "-q", *FLAGS]) == 0
    assert not _pool()
    assert cli.main(["run", str(lst), "--out", str(out3), "--ray", "--force", "--keep-workers", "1", "-q",
                     *FLAGS]) == 0
    assert _pool()
    t = time.time()
    while _pool() and time.time() - t < 20:
        time.sleep(0.2)
    assert not _pool(), "idle pooled workers did not exit"


def test_worker_not_needed_joins_the_pool(cluster, dataset, tmp_path, capsys):
    """A job with fewer tasks than the workers it asked for (or that ends before some are up)
    leaves those workers warm in the pool, not killed: the next job claims them all (a killed one
    cost the next job its whole start, ~6 s on a GPU host)."""
    lst, _ = dataset
    _empty_pool()
    one = tmp_path / "one.txt"
    one.write_text(f"{lst.parent / 'sim' / 's0'}\n")
    flags = ["--ray", "--max-tasks", "2", "--keep-workers", "30", *FLAGS]
    assert cli.main(["run", str(one), "--out", str(tmp_path / "a"), "-q", *flags]) == 0
    t = time.time()
    while len(_pool()) < 2 and time.time() - t < 30:  # the unused one joins once it is up
        time.sleep(0.2)
    assert len(_pool()) == 2
    capsys.readouterr()
    assert cli.main(["run", str(lst), "--out", str(tmp_path / "b"), *flags]) == 0
    assert "2 of them warm from the pool" in capsys.readouterr().err
    _empty_pool()


class _Killer(threading.Thread):
    """SIGKILLs a worker actor's process once ``out`` holds a frame (the workers still have frames
    to write then), and watches every output file: one replaced after it first appeared (another
    inode) was written twice."""

    def __init__(self, out: Path):
        super().__init__(daemon=True)
        self.out, self.killed, self.stop = out, None, False
        self.inodes: dict = {}
        self.rewritten: list = []

    def _watch(self):
        for p in self.out.rglob("*.npz"):
            try:
                ino = p.stat().st_ino
            except OSError:
                continue
            if self.inodes.setdefault(p, ino) != ino:
                self.rewritten.append(p)
                self.inodes[p] = ino

    def run(self):
        while not self.stop:
            self._watch()
            if self.killed is None:
                pids = [int(p) for p in os.listdir("/proc")
                        if p.isdigit() and cmdline(p).startswith("ray::FloxelsWorker") and _ours(int(p))]
                if pids and self.inodes:
                    os.kill(pids[0], signal.SIGKILL)
                    self.killed = pids[0]
            time.sleep(0.01)


def _ours(pid: int) -> bool:
    """Whether the process descends from this one (a worker of this test's cluster, whose raylet
    this process started; other jobs on the machine may run Ray workers too)."""
    for _ in range(6):
        try:
            with open(f"/proc/{pid}/stat") as f:
                pid = int(f.read().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            return False
        if pid == os.getpid():
            return True
        if pid <= 1:
            return False
    return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="finds the worker's process id in /proc")
@pytest.mark.parametrize("workers,retries", [(2, 0), (2, 2), (1, 0)])
def test_worker_killed_then_rerun(cluster, dataset, tmp_path, capsys, workers, retries):
    lst, local = dataset
    out = tmp_path / "ray"
    cmd = ["run", str(lst), "--out", str(out), "--ray", "--task-frames", "2", "--max-tasks", str(workers),
           "--retries", str(retries), "--keep-workers", "0", *FLAGS]
    _empty_pool()
    killer = _Killer(out)
    rc, err = run_beside(killer, cmd, capsys)
    assert killer.killed is not None, "no worker was killed"
    assert not killer.rewritten, f"written twice: {killer.rewritten}"
    assert "1 worker(s) lost" in err, err
    if workers > 1 or retries:  # the other worker (or a replacement) took the killed one's tasks over
        assert rc == 0, err
        _assert_same(out, local)
    else:  # no worker left: reported by file name
        assert rc == 1 and "no worker left" in err and "failed:" in err, err
        assert "not written: " in err
    assert not list(out.rglob(".*.tmp"))
    before = output_stamps(out)
    stale = out / "sim/s0" / ".000001.npz.4242.tmp"   # as if a writer had died without cleaning up
    stale.write_bytes(b"x")
    assert cli.main(cmd) == 0
    err = capsys.readouterr().err
    assert f"{len(before)} already done" in err
    after = output_stamps(out)
    assert {p: after[p] for p in before} == before, "a frame was written twice"
    _assert_same(out, local)


def test_tail_tasks_halved_same_outputs(cluster, dataset, tmp_path, monkeypatch, capsys):
    """The tasks handed out last are halved (at multiples of --chunk) so that the workers end
    together: more tasks than planned, and the outputs and each sequence's summary are the
    local run's."""
    from floxels_ext.lidar.dataset import ray_runner

    lst, local = dataset
    monkeypatch.setattr(ray_runner, "TAIL_SPLIT_FRAMES", 1)  # 4-frame sequences: halves of 2, then of 1
    out = tmp_path / "ray"
    assert cli.main(["run", str(lst), "--out", str(out), "--ray", "--max-tasks", "2", "--keep-workers", "0",
                     *FLAGS]) == 0
    err = capsys.readouterr().err
    assert "12 to estimate in 3 task(s) on Ray" in err
    job = json.loads((out / "ray_job_summary.json").read_text())
    assert job["tasks"]["done"] > 3 and job["frames_written"] == 12
    _assert_same(out, local)
    _assert_summaries(out, local)


def test_tail_cut_where_the_share_says_same_outputs(cluster, dataset, tmp_path, monkeypatch):
    """The driver cuts a task it hands out where ``ray_tail.first_part`` says (here: after its
    first frame, once), queues the rest, and the job's outputs and summaries are the local
    run's; ``tasks_run`` in the job summary names each task's frames and worker."""
    from floxels_ext.lidar.dataset import ray_runner

    lst, local = dataset
    calls = []

    def first_part(tail, worker, frames, queued, held, now):
        calls.append((worker, frames, len(queued), dict(held), tail))
        return 1.0 if len(calls) == 1 else None

    monkeypatch.setattr(ray_runner, "TAIL_SPLIT_FRAMES", 1)
    monkeypatch.setattr(ray_runner, "first_part", first_part)
    out = tmp_path / "ray"
    assert cli.main(["run", str(lst), "--out", str(out), "--ray", "--max-tasks", "2", "--keep-workers", "0",
                     *FLAGS, "-q"]) == 0
    job = json.loads((out / "ray_job_summary.json").read_text())
    assert job["tasks"]["done"] == 4 and job["frames_written"] == 12
    frames = sorted(r["task"].rsplit(" frames ", 1)[1] for r in job["tasks_run"])
    assert frames == ["0:1", "0:4", "0:4", "1:4"], frames
    assert {r["outcome"] for r in job["tasks_run"]} == {"done"}
    ends = [r["ended_s"] for r in job["tasks_run"]]  # when the driver learnt of each end, in that order
    assert ends == sorted(ends) and 0 < ends[-1] <= job["wall_s"], ends
    assert {r["worker"] for r in job["tasks_run"]} <= {w["name"] for w in job["workers"]}
    assert calls[0][1] == 4 and calls[0][2] == 2  # the first hand-out: 4 frames, 2 tasks queued behind it
    tail = calls[0][4]  # the driver's rates: every worker that wrote frames reported them
    assert set(tail.since) == {r["worker"] for r in job["tasks_run"]}
    _assert_same(out, local)
    _assert_summaries(out, local)


def test_tail_halves_inside_a_chunk_same_bytes(cluster, tmp_path, monkeypatch, capsys):
    """A tail half that starts inside a chunk (here every cut: one chunk of 8 frames) keeps the
    chunk's anchor, so a Ray job's bytes do not depend on where its timing cut the tasks: the
    local run's exactly (the sensor moves 6 m a frame; before, each half re-centred on its own
    first frame)."""
    from floxels_ext.lidar.dataset import ray_runner
    from moving_seq import moving_kitti_sequence

    velo, poses = moving_kitti_sequence(tmp_path / "in", 8)
    lst = tmp_path / "list.txt"
    lst.write_text(f"{velo} --poses {poses}\n")
    flags = ["--device", "cpu", "--max-iters", "3", "--scans", "3", "--chunk", "8", "-q"]
    assert cli.main(["run", str(lst), "--out", str(tmp_path / "local"), *flags]) == 0
    monkeypatch.setattr(ray_runner, "TAIL_SPLIT_FRAMES", 1)
    out = tmp_path / "ray"
    assert cli.main(["run", str(lst), "--out", str(out), "--ray", "--max-tasks", "2", "--keep-workers", "0",
                     *flags]) == 0
    assert json.loads((out / "ray_job_summary.json").read_text())["tasks"]["done"] > 2
    names = sorted(p.relative_to(tmp_path / "local") for p in (tmp_path / "local").rglob("*.npz"))
    assert len(names) == 8
    for rel in names:
        a, b = read_flow_output(out / rel), read_flow_output(tmp_path / "local" / rel)
        assert np.array_equal(a["flow"], b["flow"]) and np.array_equal(a["dynamic"], b["dynamic"]), rel
