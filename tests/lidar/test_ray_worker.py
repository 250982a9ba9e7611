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


def test_default_workers_a_gpu_follow_the_local_engines():
    """On a GPU cluster a worker asks for 1/W of a GPU by default, W the local run's engines on a
    host of the GPU nodes' cores per GPU (3, 4 with `accurate`, on 16+ cores a GPU; else 2), and
    the node's CPUs are split between the workers it holds."""
    from types import SimpleNamespace

    from floxels_ext.lidar.dataset import engine_counts
    from floxels_ext.lidar.dataset.ray_runner import _resources, task_slots

    nodes = [{"Alive": True, "Resources": {"CPU": 64.0, "GPU": 4.0}}]
    ray = SimpleNamespace(nodes=lambda: nodes)

    def args(**kw):
        return SimpleNamespace(**{"gpus_per_task": None, "cpus_per_task": None, "device": None, "preset": "paper",
                                  **kw})

    assert _resources(ray, args()) == (0.3333, 5.0, "cuda")
    assert task_slots([nodes[0]["Resources"]], 0.3333, 5.0) == 12
    assert _resources(ray, args(preset=None)) == (0.25, 4.0, "cuda")  # floxels run's default: accurate
    assert task_slots([nodes[0]["Resources"]], 0.25, 4.0) == 16
    assert _resources(ray, args(preset="accurate", method="floxels")) == (0.25, 4.0, "cuda")
    assert _resources(ray, args(gpus_per_task=1.0)) == (1.0, 16.0, "cuda")
    assert _resources(ray, args(device="cpu")) == (0.0, 1.0, "cpu")
    # the fewest cores a GPU decides (a worker fits any GPU node), below 16 two a GPU
    small = {"CPU": 16.0, "GPU": 2.0}
    assert engine_counts.gpu_share([nodes[0]["Resources"], small], "accurate") == 0.5
    assert engine_counts.gpu_share([{"CPU": 16.0, "GPU": 1.0}], "paper") == 0.3333
    assert engine_counts.gpu_share([{"CPU": 16.0, "GPU": 1.0}], "accurate") == 1 / engine_counts.ACCURATE_ENGINES
    assert engine_counts.default_engines("cuda", engine_counts.THREE_ENGINE_CORES - 1, "accurate") == 2


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


def test_claim_waits_while_the_dropped_workers_run_starts():
    """The starting job's ``run`` may come first: it waits for the worker's warm-up, then learns
    it has no task and releases it. A claim in that window waits for the release (it found the
    worker "running" and was refused at once: the next job then started 4 of its 8 workers anew,
    E6); a worker its starting job has given a task is refused at once."""
    w = ray_worker.FloxelsWorker(1, "cpu", keep_s=1e9, job="A")
    w.warm.join()
    w.running, w.jobs = True, 1  # run("A") started: still in its warm-up wait
    threading.Timer(0.3, w.release, args=("A",)).start()
    assert w.claim("B") and w.owner == "B"
    busy = ray_worker.FloxelsWorker(1, "cpu", keep_s=1e9, job="A")
    busy.warm.join()
    busy.running, busy.jobs = True, 1
    busy._took_task()  # its job's stream took a task: it is that job's
    t = time.monotonic()
    assert not busy.claim("B") and busy.owner == "A" and time.monotonic() - t < 0.5
    waiting = ray_worker.FloxelsWorker(1, "cpu", keep_s=1e9, job="A")
    waiting.warm.join()
    threading.Timer(0.3, waiting._took_task).start()  # a task comes while the claim waits
    t = time.monotonic()
    assert not waiting.claim("B") and time.monotonic() - t < 1.0


def test_late_claims_join_the_job_instead_of_holding_its_start():
    """The pool's workers that do not answer a claim within CLAIM_WAIT_S (still starting, or being
    handed over) neither hold the job's start (E7: ~7 s, the ready workers idle) nor get new
    workers started beside them (E6): the job starts with the others and takes each late one
    as its claim answers; one granted after the job has all its workers is given back."""
    from types import SimpleNamespace

    from floxels_ext.lidar.dataset import ray_pool

    class Ref:
        def __init__(self, at, ok, name):
            self.at, self.ok, self.name = at, ok, name

    waits, released, added = [], [], []

    def wait(refs, num_returns, timeout):  # a claim answers `at` seconds after it was sent
        waits.append(timeout)
        ready = sorted((r for r in refs if r.at <= timeout), key=lambda r: r.at)[:num_returns]
        return ready, [r for r in refs if r not in ready]

    def worker(name, at, ok):
        return SimpleNamespace(claim=SimpleNamespace(remote=lambda job: Ref(at, ok, name)),
                               release=SimpleNamespace(remote=lambda job: released.append(name)))

    handles = {"up": worker("up", 0.01, True), "busy": worker("busy", 0.01, False),
               "starting": worker("starting", 5.0, True), "slow": worker("slow", 60.0, True)}
    fake = SimpleNamespace(wait=wait, get=lambda r: r.ok, exceptions=SimpleNamespace(RayError=RuntimeError))
    pool = ray_pool.Workers(fake, 0.5, 8.0, "cuda", keep_s=120.0, t0=0.0)
    pool._pooled = lambda: [f"w-{pool.key}-{n}" for n in handles]
    pool._handle = lambda nm: handles[nm.rsplit("-", 1)[1]]
    pool._retire_idle = lambda keep: None
    pool.add = lambda: added.append(1)
    pool.start(4)
    assert [s.name.rsplit("-", 1)[1] for s in pool.slots] == ["up"] and waits == [ray_pool.CLAIM_WAIT_S]
    assert sorted(r.name for r in pool.late) == ["slow", "starting"]
    assert len(added) == 1  # 4 wanted: 1 up, 2 coming, "busy" refused: one new worker
    late = {r.name: r for r in pool.late}
    assert pool.take_late(late["starting"]).name.endswith("starting") and len(pool.slots) == 2
    pool.target = 2  # the job has all it needs now: a late one granted after it goes back
    assert pool.take_late(late["slow"]) is None and released == ["slow"] and not pool.late


def test_release_before_its_claim_withdraws_the_claim():
    """A job that ends while its claim still waits in a worker's queue releases it at once; a
    threaded actor may run that release first, and the claim must then be refused (it would hold
    the worker for OWNER_TIMEOUT, its driver gone)."""
    w = ray_worker.FloxelsWorker(1, "cpu", keep_s=1e9, job=None)
    w.warm.join()
    w.release("gone")
    assert not w.claim("gone") and w.owner is None and w.claim("next")
