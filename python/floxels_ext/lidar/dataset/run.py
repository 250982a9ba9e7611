"""``floxels run INPUT --out OUT [--ray [auto|ADDRESS]]``: where INPUT goes. One sequence runs
here as one task (``local.run_sequence``); a dataset (a directory of sequences or a list file)
as one task per sequence through one pipeline here (``local.run_dataset``), or through one per
worker on a Ray cluster (``ray_runner``), as does any INPUT with ``--ray``. With ``--engines N``
(default on CUDA 3 with 16+ cores, else 2) the sequences are cut into tasks of ``--task-frames`` for N engines on this
machine's device (``engines``). All of them run their tasks through the same engine
(``worker``, ``stream``).

``floxels_ext.lidar.run`` calls two functions of this module: ``add_dataset_arguments(parser)``
while building its parser and ``run_input(args)`` to run.

A task is a sequence's frames ``[A, B)`` with the user's other options: its outputs are those
of ``floxels run SEQ --out OUT/<rel> --frames A:B`` (``sequence`` opens every task alike:
checks, windows, metadata). Output files are written atomically under temporary
names ``.<frame>.npz.<pid>.tmp``; several tasks of one sequence may share an output directory,
so a task removes only the temporaries of its own frames (left by an earlier, killed attempt),
and the Ray driver sweeps the rest before launching and after the last task.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from floxels_ext.lidar.dataset.engine_counts import default_engines

__all__ = ["add_dataset_arguments", "run_input"]

MAX_ENGINES = 8  # engines on one device: more contexts than this only queue behind each other
RAY_TASK_FRAMES = 192


def add_dataset_arguments(p: argparse.ArgumentParser) -> None:
    import textwrap

    from floxels_ext.cli_types import finite_float

    g = p.add_argument_group("datasets and clusters", textwrap.fill(
        "INPUT may also be a dataset: a directory holding sequences at any depth (an Argoverse 2 split "
        "of log folders, KITTI odometry with sequences/NN/velodyne and poses/NN.txt, a directory of "
        "'floxels simulate' sequences; frame files beside sequences are refused) or a text file listing sequence directories (one a line, "
        "optionally 'PATH --poses FILE --calib FILE'). OUT then mirrors the input tree. Without --ray "
        "the sequences run here, one after another through one pipeline (the next one read while the "
        "current one is estimated); with --ray, several workers per GPU do the same with the sequences it "
        "takes from the driver.", 92))
    g.add_argument("--ray", nargs="?", const="auto", metavar="auto|ADDRESS",
                   help="run on a Ray cluster, long-lived workers, several per GPU (pip install 'floxels_ext[ray]'): "
                        "'auto' (the default "
                        "when the flag is bare) joins the cluster this machine belongs to or starts a local "
                        "one; ADDRESS is a head node (host:6379 or ray://host:10001)")
    g.add_argument("--gpus-per-task", type=finite_float, metavar="G",
                   help="GPUs a worker asks Ray for; fractions pack several workers on a GPU (default when the "
                        "cluster has GPUs and --device is not cpu: as many workers a GPU as --engines' default "
                        "on a host of the GPU nodes' cores per GPU: 1/3, 1/4 with the accurate preset, with 16+ "
                        "cores a GPU, else 0.5; no GPUs: 0 = CPU workers; 1: one worker a GPU, for GPUs too small "
                        "for several)")
    g.add_argument("--cpus-per-task", type=finite_float, default=None, metavar="C",
                   help="CPUs a worker asks Ray for (its reader threads and torch threads; default: a GPU "
                        "node's CPUs shared by its GPU workers, 1 for CPU workers)")
    g.add_argument("--max-tasks", type=int, metavar="N", help="at most N workers (default: as many as the "
                   "cluster's resources fit)")
    g.add_argument("--task-frames", type=int, default=None, metavar="N",
                   help="frames per task (what an engine or a Ray worker takes at a time): longer sequences "
                        "are cut into tasks (rounded up to a multiple of --chunk, else of 64; support scans beyond "
                        "a task are still read, and the outputs do not depend on the cut); 0 = whole sequences "
                        "(default: with --engines, --chunk (128): no method call is cut; fewer, multiples of "
                        "64, for a run of few frames, so that each engine gets three tasks; with --ray, 192)")
    g.add_argument("--retries", type=int, default=3, metavar="N",
                   help="workers started in place of ones that died, at most (default 3); a dead worker's "
                        "tasks go to the others in any case")
    g.add_argument("--keep-workers", type=finite_float, default=120.0, metavar="S",
                   help="with --ray: the workers stay warm (process, CUDA context, kernels) for S seconds after "
                        "the job, for the next job on the same cluster with the same options, then exit and free "
                        "their GPUs (default 120); 0 = they stop with the job")
    g.add_argument("--engines", type=int, default=None, metavar="N",
                   help="engines on this machine's one device: the run's own process is engine 0 and starts at "
                        "once, N-1 processes start beside it and take tasks (--task-frames) from one queue when "
                        "ready. Two keep a GPU busy through each other's host steps (1.41x the frames/s of one, "
                        "measured; three on a host of 16+ cores, 1.02-1.58x two); the outputs are the same bytes "
                        "whatever N. Default on CUDA: 3 with 16+ cores (4 with --preset accurate, the default), else 2; 1 on the CPU (whose cores one engine "
                        f"already uses); 1: one engine in this process; at most {MAX_ENGINES}")
    g.add_argument("--mps", choices=["auto", "on", "off"], default="auto",
                   help="engines sharing a GPU run their kernels side by side through CUDA MPS, in a private "
                        "daemon started for the run and stopped after it (1.11-1.21x the frames/s of --preset "
                        "accurate with four engines on an H100, measured; the same outputs). auto (default): "
                        "when several engines share a GPU, nvidia-cuda-mps-control is on the PATH and no MPS is "
                        "set up already (CUDA_MPS_PIPE_DIRECTORY: yours is used); on: the same, an error if it "
                        "cannot start; off: none is started")
    g.add_argument("--sequences", action="append", metavar="GLOB",
                   help="only the sequences whose output sub-path matches this shell pattern (e.g. "
                        "'sequences/0[0-9]/*'); repeatable")


def engine_count(args) -> int:
    """``--engines``, checked (CLIError), or its default (``engine_counts.default_engines``: on
    CUDA with 16+ cores 3, 4 with the ``accurate`` preset, floxels run's default, else 2; 1 on
    the CPU, also with --ray, whose workers are the engines, and with --worker-kind process)."""
    from floxels_ext.errors import CLIError

    n = args.engines
    if n is None:
        if args.ray is not None or args.worker_kind == "process":
            return 1
        import torch

        from floxels_ext.lidar.pipeline.run_args import preset_name

        device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
        return default_engines(device, preset=preset_name(args))
    if args.ray is not None:
        raise CLIError("--engines runs engines on this machine; it contradicts --ray, whose workers are the engines "
                       "(--gpus-per-task 0.25: four a GPU)")
    if not 1 <= n <= MAX_ENGINES:
        raise CLIError(f"--engines must be in [1, {MAX_ENGINES}] (engines sharing this machine's one device), got {n}")
    if n > 1 and args.worker_kind == "process":
        raise CLIError(f"--engines {n} runs its engines as processes, with reader and writer threads; it "
                       f"contradicts --worker-kind process")
    return n


def _forks_ahead(args) -> bool:
    """Whether the run will likely start processes from the fork server: engines (``--engines``
    N > 1, or by default where a GPU is present) or ``--worker-kind process``'s readers and
    writers. Told without importing torch: an NVIDIA device node, and CUDA_VISIBLE_DEVICES not
    hiding every GPU. A wrong guess costs a background import, never a wrong run."""
    if args.ray is not None:
        return False  # the engines are Ray's workers, elsewhere
    if args.worker_kind == "process":
        return True
    if args.engines is not None:
        return args.engines > 1
    if args.device is not None and not args.device.startswith("cuda"):
        return False
    return os.environ.get("CUDA_VISIBLE_DEVICES", "0").strip() not in ("", "-1") and os.path.exists("/dev/nvidiactl")


def _start_mps(args) -> None:
    """``--mps``: a private CUDA MPS daemon for the engines that will share a GPU
    (``dataset/mps.py``), started before the run touches CUDA, so its engine count is taken
    without asking torch for a GPU (the default count on CUDA; on the CPU no MPS starts)."""
    from floxels_ext.lidar.dataset.mps import use_mps
    from floxels_ext.lidar.pipeline.run_args import preset_name

    if args.engines is not None:
        n = engine_count(args)  # checked (no CUDA call when given)
    elif args.ray is not None or args.worker_kind == "process":
        n = 1
    else:
        n = default_engines("cuda", preset=preset_name(args))
    use_mps(args.mps, args.device, n, args.ray is not None)


def _check_options(args, dataset: bool, engines: int = 1) -> None:
    from floxels_ext.errors import CLIError

    if args.ray is None:
        used = [f for f, v, default in (("--gpus-per-task", args.gpus_per_task, None),
                                        ("--max-tasks", args.max_tasks, None), ("--cpus-per-task", args.cpus_per_task, None),
                                        ("--retries", args.retries, 3), ("--keep-workers", args.keep_workers, 120.0))
                if v != default]
        if used:
            raise CLIError(f"{', '.join(used)} only {'applies' if len(used) == 1 else 'apply'} with --ray")
        if args.task_frames is not None and engines == 1:
            raise CLIError("--task-frames only applies with --ray or --engines N > 1 (one engine runs whole sequences)")
    if dataset and (args.poses or args.calib):
        raise CLIError("--poses/--calib name one sequence's files; a dataset's are found per sequence (KITTI "
                       "poses/NN.txt and sequences/NN/calib.txt) or given per line of a list file "
                       "('PATH --poses FILE --calib FILE')")
    if args.gpus_per_task is not None and args.gpus_per_task < 0:
        raise CLIError(f"--gpus-per-task must be >= 0, got {args.gpus_per_task}")
    if args.gpus_per_task and args.device == "cpu":
        raise CLIError("--gpus-per-task > 0 contradicts --device cpu")
    if args.cpus_per_task is not None and args.cpus_per_task <= 0:
        raise CLIError(f"--cpus-per-task must be > 0, got {args.cpus_per_task}")
    if args.max_tasks is not None and args.max_tasks < 1:
        raise CLIError("--max-tasks must be >= 1")
    if args.task_frames is not None and args.task_frames < 0:
        raise CLIError("--task-frames must be >= 0 (0 = whole sequences)")
    if args.retries < 0:
        raise CLIError("--retries must be >= 0")
    if args.keep_workers < 0:
        raise CLIError(f"--keep-workers must be >= 0 seconds, got {args.keep_workers}")


def run_input(args) -> int:
    """Runs INPUT: one sequence (here, or through Ray with ``--ray``) or a dataset."""
    if args.ray is None or not args.input or not args.out or not Path(args.input).exists():
        return _run_input(args, None)  # (a missing INPUT is reported without starting Ray)
    from floxels_ext.lidar.dataset.ray_runner import early_workers

    _check_options(args, dataset=False)
    engine_count(args)  # --engines contradicts --ray: said before Ray starts
    _start_mps(args)  # (--mps on contradicts --ray: said before Ray starts too)
    with early_workers(args) as workers:  # they start while the dataset is listed and planned
        return _run_input(args, workers)


def _run_input(args, workers) -> int:
    from floxels_ext.lidar.dataset.engines import early_engines
    from floxels_ext.lidar.pipeline.run_args import require_input_and_out

    require_input_and_out(args)
    _start_mps(args)  # before this process touches CUDA (engine_count may ask torch for a GPU)
    if _forks_ahead(args):
        from floxels_ext.lidar.pipeline.worker_processes import start_forkserver

        # after the MPS set-up (the server's children inherit its environment), before this
        # process imports torch (4-5 s on a CUDA image): the two imports run side by side, and
        # the engines join seconds sooner (a fresh 768-frame run: 1.14-1.28x the frames/s,
        # bench/RESULTS.md, "Where a 768-frame `floxels run` loses half its rate")
        start_forkserver()
    engines = engine_count(args)
    device = None
    if engines > 1:
        import torch

        device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    # engines 1..N-1 start now: their start (process, imports, CUDA context) overlaps the listing
    with early_engines(args, engines, device) as pool:
        return _run_tasks(args, workers, engines, pool)


def _run_tasks(args, workers, engines: int, pool) -> int:
    from floxels_ext.errors import CLIError
    from floxels_ext.lidar.dataset.local import run_dataset, run_sequence
    from floxels_ext.lidar.dataset.tasks import (SequenceSpec, balanced_task_size, discover_dataset, plan_tasks,
                                                 task_size)

    specs = discover_dataset(args.input, args.out, args.sequences)
    _check_options(args, specs is not None, engines)
    align = args.chunk or 64  # 64: half the run's default chunk
    if args.ray is not None:
        task_frames = RAY_TASK_FRAMES if args.task_frames is None else args.task_frames
    elif engines > 1:  # tasks of one chunk: the method's calls are those of one engine, none cut
        from floxels_ext.lidar.dataset.layout import DEFAULT_CHUNK

        task_frames = (args.chunk or DEFAULT_CHUNK) if args.task_frames is None else args.task_frames
    else:
        task_frames = 0
    if specs is None:
        if args.sequences:
            raise CLIError(f"--sequences selects sequences of a dataset, but {args.input} is one sequence")
        if args.ray is None:
            # KISS-ICP runs over a whole sequence once: one task (as plan_tasks does)
            size = 0 if args.odometry or args.chunk is not None and args.chunk < 1 else task_size(task_frames, align)
            return run_sequence(args, pool, size, align)
        specs = [SequenceSpec(Path(args.input).resolve(), Path("."),
                              Path(args.poses) if args.poses else None, Path(args.calib) if args.calib else None)]
    from floxels_ext.lidar.pipeline.run_args import resolve_preset

    resolve_preset(args)  # --scans from the preset when not given
    if not 2 <= args.scans <= 13:
        raise CLIError(f"--scans must be in [2, 13], got {args.scans}")
    if args.chunk is not None and args.chunk < 1:
        raise CLIError("--chunk must be >= 1")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise CLIError(f"--out {out} exists and is not a directory")
    from floxels_ext.output_paths import check_writable_dir

    check_writable_dir(out, "--out")  # before any sequence is opened (a read-only place)
    tasks, problems = plan_tasks(specs, out, args, task_frames=task_frames, align=align)
    if problems:
        raise CLIError(f"{len(problems)} of the {len(specs)} sequences cannot run (fix them or leave them out "
                       f"with --sequences):\n  " + "\n  ".join(problems))
    written: dict = {}  # out_dir -> names of its outputs: one listing a sequence, not a stat a frame
    _set_todo(tasks, args, written)
    if pool is not None and args.task_frames is None:  # few frames for the engines: smaller tasks
        planned = task_size(task_frames, align)
        size = balanced_task_size(sum(len(t.todo) for t in tasks), engines, planned, align)
        if size != planned:  # (the sequences listed again: only a run of few frames gets here)
            tasks, _ = plan_tasks(specs, out, args, task_frames=size, align=align)
            _set_todo(tasks, args, written)
    _check_written_tasks([t for t in tasks if not t.todo], args)
    from floxels_ext.lidar.dataset.tasks import common_options

    common = common_options(args)
    if args.ray is not None:
        from floxels_ext.lidar.dataset.ray_runner import run_on_ray

        # tail halves may cut anywhere: a chunk's anchor is its block's (layout.plan_chunks),
        # whichever task holds it (KISS-ICP, --task-frames 0: whole sequences, never cut)
        split = 0 if args.odometry or task_frames <= 0 else 1
        return run_on_ray(tasks, args, common, n_sequences=len(specs), workers=workers, align=split)
    return run_dataset(tasks, args, n_sequences=len(specs), engines=pool)


def _set_todo(tasks, args, written: dict) -> None:
    """Each task's frames left to do (the run skips written frames the same way); ``written``:
    out_dir -> names of its outputs, filled as sequences are listed (one listing a sequence)."""
    from floxels_ext.lidar.dataset.tasks import written_names

    for t in tasks:
        if args.force:
            t.todo = list(t.names)
            continue
        if t.out_dir not in written:
            written[t.out_dir] = written_names(t.out_dir)
        t.todo = [n for n in t.names if n not in written[t.out_dir]]


def _check_written_tasks(tasks, args) -> None:
    """Tasks whose outputs all exist get the resume check of ``floxels run SEQ``
    (``sequence.resume_todo``): outputs written from other inputs (their window's scans, poses
    or times changed since) are estimated again. A task that cannot be checked (other settings,
    unreadable poses) goes to the workers, whose ``open_sequence`` fails it with the reason."""
    if not tasks:
        return
    from floxels_ext.errors import CLIError
    from floxels_ext.evaluation.seqio import SequenceFormatError
    from floxels_ext.lidar.dataset.sequence import resume_todo
    from floxels_ext.lidar.io import MissingDependencyError
    from floxels_ext.lidar.pipeline.run_args import method_options, preprocess_settings

    options, settings = method_options(args), preprocess_settings(args)  # what the workers' check_args gives
    for t in tasks:
        try:
            t.todo = resume_todo(t, args, options, settings)
        except (CLIError, SequenceFormatError, MissingDependencyError, OSError, ValueError):
            t.todo = list(t.names)
