"""One engine process of ``floxels run --engines N`` (engines 1..N-1; engine 0 is the run's own
process): the child's side of the hand-out that ``engines`` runs.

It comes from the fork server (``pipeline/worker_processes``: a clean, single-threaded parent, so
no lock some thread of the run held is copied into it), sets its CPU threads to its share of
the host, warms up (imports, CUDA context, a tiny estimate: ``ray_worker.warm_up``), says
"ready", and then runs the same pipeline as every run (``worker.run_tasks``) over the tasks it
asks the run for (after its options: the engines start before the run has planned its tasks),
one at a time, through its pipe, exactly as a Ray worker asks its driver
(``ray_worker.Channel``): "need" while its stream has work ahead (answer: a task, "wait": none
queued now, the stream drains; None: the run is over) and "idle" once drained (the run answers
when another engine's task comes back, or None). Everything it has to say goes up the pipe:
frames done, tasks ended with their summary part, warnings; it prints nothing itself.

Ctrl-C: it ignores SIGINT (the terminal sends it to the whole process group); the run forwards
the interrupt as SIGTERM, which stops the stream like Ctrl-C stops the run's own (results
already computed are written, atomically; no half-written output).
"""

from __future__ import annotations

import os
import signal
import threading
import time

__all__ = ["engine_main"]


def _interrupt(signum, frame) -> None:
    raise KeyboardInterrupt


def engine_main(conn, index: int, device: str, threads: dict) -> None:
    """The process's target (``engines.Engines``): ``conn`` its end of the pipe to the run."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _interrupt)
    lock = threading.Lock()  # the pipe is written from the stream's threads and this one

    def send(msg) -> None:
        with lock:
            conn.send(msg)

    try:
        _serve(conn, send, index, device, threads)
    except (KeyboardInterrupt, BrokenPipeError, EOFError):
        pass  # stopped by the run, or the run is gone
    except BaseException as e:  # noqa: BLE001 - said to the run, which hands the task to another engine
        try:
            send(("error", f"{type(e).__name__}: {e}"))
        except OSError:
            pass
    finally:
        conn.close()


def _serve(conn, send, index: int, device: str, threads: dict) -> None:
    import torch

    from floxels_ext.lidar.dataset.ray_worker import task_args, warm_up

    torch.set_num_threads(threads["torch"])  # its share of the host, not an OpenMP team per core
    stamps = {"process": time.time()}
    warm_up(device, stamps)
    if device.startswith("cuda") and "warm_error" in stamps:  # e.g. a GPU that takes one context only
        raise RuntimeError(f"its warm-up on {device} failed ({stamps['warm_error']}): it takes no task")
    from floxels_ext.lidar.dataset.worker import run_tasks

    def ask(what: str):
        send((what,))
        return conn.recv()

    send(("ready", os.getpid(), stamps))
    common = ask("options")  # the run's options, once it has planned its tasks (None: it is over)
    if common is None:
        send(("done",))
        return
    args = task_args(common, device, threads)
    state = {"over": False}  # the run said None: no task will come

    def tasks(first):
        item = first
        while isinstance(item, tuple):
            k, task = item
            task.lease = k
            yield task
            item = ask("need")
        state["over"] = item is None  # else "wait": this stream drains, then it asks as "idle"

    def on_frame(job, i) -> None:
        send(("frame", job.info["task"].lease, job.seq.frames[i].name, i not in job.failed))

    def ended(task, outcome, job, lines) -> None:
        send(("ended", task.lease, outcome, list(lines), None if job is None else job.info.get("summary")))

    item = ask("need")
    while item is not None:  # one stream while tasks are queued; once drained, wait for one handed back
        if item != "wait":
            r = run_tasks(tasks(item), args, report=lambda msg: send(("report", msg)), on_frame=on_frame,
                          on_sequence=ended, engine=index)
            send(("stages", r["stages"]))  # the stream's stage times, its wall included
            if state["over"]:
                break
        item = ask("idle")
    send(("done",))
