"""The Ray worker's parts that need no cluster: the task hand-out between its pipeline and the
driver (``ray_worker.Channel``), the CPU threads it takes from the CPUs Ray gave it
(``worker_threads``) and the run options it builds from them (``task_args``)."""

import threading
import time

from floxels_ext.lidar.dataset import ray_worker
from floxels_ext.lidar.dataset.ray_worker import Channel, task_args, worker_threads


def test_worker_threads_rule():
    # a GPU worker: a few torch threads, readers leaving a core to the main thread and one to the rest
    assert worker_threads(16, gpu=True) == {"cpus": 16, "torch": 4, "readers": 6, "writers": 2}
    assert worker_threads(8, gpu=True) == {"cpus": 8, "torch": 4, "readers": 6, "writers": 2}
    assert worker_threads(4, gpu=True) == {"cpus": 4, "torch": 4, "readers": 2, "writers": 2}
    assert worker_threads(2, gpu=True) == {"cpus": 2, "torch": 2, "readers": 1, "writers": 2}
    assert worker_threads(0.5, gpu=True)["readers"] == 1
    # a CPU worker computes in torch's ops: all its CPUs
    assert worker_threads(16, gpu=False) == {"cpus": 16, "torch": 16, "readers": 6, "writers": 2}
    assert worker_threads(1, gpu=False) == {"cpus": 1, "torch": 1, "readers": 1, "writers": 2}


def test_task_args_threads_and_user_settings():
    common = {"method": "floxels", "workers": None, "writers": None, "scans": 3}
    ns = task_args(common, "cuda", worker_threads(16, gpu=True))
    assert (ns.device, ns.workers, ns.writers, ns.cpu_limit, ns.ray) == ("cuda", 6, 2, 16, None)
    ns = task_args(dict(common, workers=3, writers=5), "cpu", worker_threads(2, gpu=False))
    assert (ns.workers, ns.writers, ns.cpu_limit) == (3, 5, 2)  # the user's --workers/--writers win


def test_channel_hand_out():
    ch = Channel()
    got = []

    def pipeline():  # a stream: its tasks until "wait", then (drained) asks again as "idle"
        got.append(list(ch.tasks()))
        got.append(ch.ask("idle"))
        got.append(list(ch.tasks(first=got[-1])))

    t = threading.Thread(target=pipeline)
    t.start()
    answers = iter([(0, "a"), (1, "b"), "wait", (2, "c"), None])
    seen = []
    while t.is_alive() or ch.events:
        events, _ = ch.poll(0.2)
        for ev in events:
            seen.append(ev[0])
            if ev[0] in ("need", "idle"):
                ch.answers.put(next(answers))
        if not t.is_alive():
            break
    t.join(5)
    assert got == [[(0, "a"), (1, "b")], (2, "c"), [(2, "c")]]
    assert seen == ["need", "need", "need", "idle", "need"] and ch.over


def test_channel_poll_reports_and_closes():
    ch = Channel()
    ch.count(3)
    ch.count(3)
    ch.count(5)
    t = time.monotonic()
    events, frames = ch.poll(0.3)  # nothing to say: returns after the timeout, with the frame counts
    assert events == [] and frames == {3: 2, 5: 1} and time.monotonic() - t >= 0.25
    ch.emit("ended", 3, "done", [])
    assert ch.poll(5.0) == ([("ended", 3, "done", [])], {})
    ch.close()
    assert ch.poll(5.0) == ([("closed",)], {})


def test_channel_gives_up_without_driver(monkeypatch):
    monkeypatch.setattr(ray_worker, "OWNER_TIMEOUT", 0.3)
    ch = Channel()
    ch.seen -= 1.0  # the driver's last poll was long ago: it is gone
    assert list(ch.tasks()) == [] and ch.ask("idle") is None


def test_retire_while_held_exits_on_release(monkeypatch):
    """A job that needs a held worker's resources asks it to retire; the worker leaves as soon
    as its job releases it (a job finishing its last frames), not after the pool's idle time."""
    exits = []  # (keep_s: never idle long enough to exit by itself, after the patch is undone too)
    monkeypatch.setattr(ray_worker.FloxelsWorker, "_exit", lambda self: exits.append(1))
    w = ray_worker.FloxelsWorker(1, "cpu", keep_s=1e9, job="A")
    w.warm.join()
    assert w.retire() is False          # held by job A
    assert not w.claim("B")             # leaving: no other job takes it meanwhile
    w.release("A")
    t = time.time()
    while not exits and time.time() - t < 5:
        time.sleep(0.01)
    assert exits == [1] and w.retiring
    idle = ray_worker.FloxelsWorker(1, "cpu", keep_s=1e9, job="A")
    idle.warm.join()
    idle.release("A")                   # no retire asked: it stays in the pool
    time.sleep(0.1)
    assert len(exits) == 1 and not idle.retiring and idle.claim("C")


def test_default_two_workers_a_gpu():
    """On a GPU cluster a worker asks for half a GPU by default (two share each GPU: one leaves
    its GPU idle during its host steps) and the node's CPUs are split between them."""
    from types import SimpleNamespace

    from floxels_ext.lidar.dataset.ray_runner import GPU_SHARE, _resources, task_slots

    nodes = [{"Alive": True, "Resources": {"CPU": 64.0, "GPU": 4.0}}]
    ray = SimpleNamespace(nodes=lambda: nodes)

    def args(**kw):
        return SimpleNamespace(**{"gpus_per_task": None, "cpus_per_task": None, "device": None, **kw})

    assert GPU_SHARE == 0.5
    assert _resources(ray, args()) == (0.5, 8.0, "cuda")
    assert task_slots([nodes[0]["Resources"]], 0.5, 8.0) == 8
    assert _resources(ray, args(gpus_per_task=1.0)) == (1.0, 16.0, "cuda")
    assert _resources(ray, args(device="cpu")) == (0.0, 1.0, "cpu")


def test_claim_waits_for_the_starting_jobs_release():
    """A worker that a job started and dropped before it was up: that job's release and the next
    job's claim reach it together once it is up, in either order; the claim waits for the release
    instead of leaving the worker idle while the next job starts another (~6 s on a GPU host)."""
    w = ray_worker.FloxelsWorker(1, "cpu", keep_s=1e9, job="A")
    w.warm.join()
    threading.Timer(0.2, w.release, args=("A",)).start()
    t = time.monotonic()
    assert w.claim("B") and w.owner == "B"
    assert time.monotonic() - t < ray_worker.HANDOVER_S
    kept = ray_worker.FloxelsWorker(1, "cpu", keep_s=1e9, job="A")  # its job keeps it: no release comes
    kept.warm.join()
    assert not kept.claim("B") and kept.owner == "A"


def test_job_short_of_workers_waits_for_the_pools_starting_ones():
    """The pool's workers that do not answer a claim at once are still starting: a job short of
    workers waits for them (up to STARTING_WAIT_S) rather than starting new ones beside them."""
    from types import SimpleNamespace

    from floxels_ext.lidar.dataset import ray_pool

    class Ref:
        def __init__(self, at, ok):
            self.at, self.ok = at, ok

    waits = []

    def wait(refs, num_returns, timeout):  # a claim answers `at` seconds after it was sent
        waits.append(timeout)
        ready = sorted((r for r in refs if r.at <= timeout), key=lambda r: r.at)[:num_returns]
        return ready, [r for r in refs if r not in ready]

    def worker(at, ok):
        return SimpleNamespace(claim=SimpleNamespace(remote=lambda job: Ref(at, ok)),
                               release=SimpleNamespace(remote=lambda job: None))

    handles = {"up": worker(0.01, True), "busy": worker(0.01, False), "starting": worker(5.0, True),
               "late": worker(60.0, True)}
    fake = SimpleNamespace(wait=wait, get=lambda r: r.ok, exceptions=SimpleNamespace(RayError=RuntimeError))
    pool = ray_pool.Workers(fake, 0.5, 8.0, "cuda", keep_s=None, t0=0.0)
    pool._handle = handles.get
    got = pool._claim(list(handles), 3)
    assert sorted(s.name for s in got) == ["starting", "up"]
    assert waits == [ray_pool.CLAIM_WAIT_S, ray_pool.STARTING_WAIT_S]
    waits.clear()
    assert [s.name for s in pool._claim(["up", "busy"], 1)] == ["up"] and waits == [ray_pool.CLAIM_WAIT_S]
