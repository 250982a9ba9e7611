"""Worker processes of ``floxels run`` (readers with ``--worker-kind process``, writers) and the
fork server that also starts its engine processes (``--engines``, ``dataset/engines``).

They come from a fork server (``multiprocessing``'s "forkserver"), not a plain fork of the run:
the run is multi-threaded and has used torch (and CUDA) by then, and a forked copy of it
deadlocked inside its first torch op call (a lock some other thread held at the fork). The fork
server is a fresh, single-threaded interpreter that imports the package once (~2 s on a CPU
host, ~5 s on a CUDA image, once per Python process; ``floxels run`` starts it before importing
torch itself: :func:`start_forkserver`) and forks every worker from that clean state. Workers ignore Ctrl-C: the run
stops them after finishing what is queued.
"""

from __future__ import annotations

import multiprocessing as mp
from concurrent.futures import ProcessPoolExecutor

__all__ = ["process_pool", "forkserver_context", "start_forkserver"]

# what the fork server imports once for every child: the readers' and writers' modules, and
# torch with the engine (``floxels run --engines``: each engine process then starts in about the
# time of its CUDA context, not of torch's import)
_PRELOAD = ["floxels_ext.lidar.pipeline.frame_loader", "floxels_ext.lidar.pipeline.frame_writer", "torch",
            "floxels_ext.ops", "floxels_ext.methods", "floxels_ext.lidar.dataset.worker",
            "floxels_ext.lidar.dataset.engine_process"]


def _init(initializer, initargs) -> None:
    import signal

    import torch

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    torch.set_num_threads(1)  # the workers are the parallelism: no OpenMP team in each of them
    initializer(*initargs)


def _nothing() -> None:
    return None


def process_pool(workers: int, initializer, initargs: tuple) -> ProcessPoolExecutor:
    """``workers`` processes from the fork server, each running ``initializer(*initargs)``
    (pickled: module-level functions and picklable state only); started before returning."""
    ctx = forkserver_context()
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_init,
                               initargs=(initializer, initargs))
    for f in [pool.submit(_nothing) for _ in range(workers)]:
        f.result()
    return pool


def forkserver_context():
    """``multiprocessing``'s fork-server context with the package preloaded (one list for every
    caller: the fork server takes the list of its first start)."""
    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload(_PRELOAD)
    return ctx


def start_forkserver() -> None:
    """Starts the fork server now, without waiting for it: its imports (torch and the package:
    ~2 s on a CPU host, ~5 s on a CUDA image) then run beside the caller's own instead of after
    them, at the first engine's or worker's start. Returns at once; a fork server already
    running is kept. A server that cannot start now (no process left to spawn, say) is left to
    the first engine's or worker's start, which reports it as it always has."""
    from multiprocessing import forkserver

    forkserver_context()  # the preload list first: the server takes the list of its start
    try:
        forkserver.ensure_running()
    except OSError:
        pass
