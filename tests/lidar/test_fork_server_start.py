"""``floxels run`` starts its fork server early (``dataset/run._forks_ahead``,
``pipeline/worker_processes.start_forkserver``): after the MPS set-up (the server's children
inherit its environment) and before the run imports torch, wherever the run will likely fork
engines or worker processes, and nowhere else (a CPU-only run, one engine, Ray)."""

import argparse

import pytest

from floxels_ext.lidar.dataset import run as run_mod
from floxels_ext.lidar.pipeline import worker_processes


def _args(**kw) -> argparse.Namespace:
    base = dict(ray=None, worker_kind="auto", engines=None, device=None)
    base.update(kw)
    return argparse.Namespace(**base)


@pytest.fixture
def gpu_node(monkeypatch):
    """A host with (True) or without (False) an NVIDIA device node, CUDA_VISIBLE_DEVICES unset."""
    def make(present: bool):
        real = run_mod.os.path.exists
        monkeypatch.setattr(run_mod.os.path, "exists",
                            lambda p: present if p == "/dev/nvidiactl" else real(p))
        monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    return make


@pytest.mark.parametrize("kw, gpu, expected", [
    (dict(), True, True),                                # default engines on a GPU host
    (dict(), False, False),                              # CPU-only host: one engine, no fork
    (dict(device="cuda:0"), True, True),
    (dict(device="cpu"), True, False),                   # one engine on the CPU by default
    (dict(engines=2, device="cpu"), False, True),        # engines asked for, on any device
    (dict(engines=1), True, False),
    (dict(worker_kind="process", device="cpu"), False, True),  # process readers and writers
    (dict(ray="auto"), True, False),                     # Ray's workers are the engines
    (dict(ray="auto", worker_kind="process"), True, False),
])
def test_forks_ahead(gpu_node, kw, gpu, expected):
    gpu_node(gpu)
    assert run_mod._forks_ahead(_args(**kw)) is expected


@pytest.mark.parametrize("visible", ["", "-1", " "])
def test_no_fork_server_when_every_gpu_is_hidden(gpu_node, monkeypatch, visible):
    gpu_node(True)
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", visible)
    assert run_mod._forks_ahead(_args()) is False


def test_fork_server_starts_after_mps_and_before_the_engine_count(monkeypatch, tmp_path, gpu_node):
    """The order inside ``_run_input``: MPS first (its environment), then the fork server, then
    the engine count (the run's first import of torch)."""
    gpu_node(True)
    calls = []

    class Stop(Exception):
        pass

    monkeypatch.setattr(run_mod, "_start_mps", lambda args: calls.append("mps"))
    monkeypatch.setattr(worker_processes, "start_forkserver", lambda: calls.append("fork"))

    def count(args):
        calls.append("count")
        raise Stop

    monkeypatch.setattr(run_mod, "engine_count", count)
    (tmp_path / "in").mkdir()
    args = _args(input=str(tmp_path / "in"), out=str(tmp_path / "out"))
    with pytest.raises(Stop):
        run_mod._run_input(args, None)
    assert calls == ["mps", "fork", "count"]


def test_start_forkserver_returns_at_once_and_serves_children():
    """It does not wait for the server's imports, and a process started afterwards comes from it."""
    import time

    t0 = time.perf_counter()
    worker_processes.start_forkserver()
    assert time.perf_counter() - t0 < 1.0  # the server's preload (torch: seconds) runs beside the caller
    ctx = worker_processes.forkserver_context()
    p = ctx.Process(target=int)
    p.start()
    p.join(60)
    assert p.exitcode == 0


def test_a_fork_server_that_cannot_start_early_is_left_to_the_engines(monkeypatch):
    """An OSError at the early start (no process left to spawn) is not the run's crash: the
    engines' own start reports it later (``Engines._start_all``: a lost engine)."""
    from multiprocessing import forkserver

    def fail():
        raise OSError(11, "Resource temporarily unavailable")

    monkeypatch.setattr(forkserver, "ensure_running", fail)
    worker_processes.start_forkserver()  # no exception
