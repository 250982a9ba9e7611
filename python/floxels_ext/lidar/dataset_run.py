"""``floxels run DATASET --out OUT [--ray [auto|ADDRESS]]``: every sequence of a dataset, one after
another on the local device or as tasks on a Ray cluster (``ray_runner``).

``floxels_ext.lidar.run`` calls two functions of this module: ``add_dataset_arguments(parser)`` while
building its parser and ``maybe_run_dataset(args)`` first thing in ``run(args)``; the latter
returns None when INPUT is one sequence and ``--ray`` is not given (the plain run goes on).

A task is one ``floxels run SEQ --out OUT/<rel> --frames A:B`` with the user's other options,
parsed by the same parser, so its output is the one the local run writes. Output files are
written atomically under temporary names ``.<frame>.npz.<pid>.tmp``; several tasks of one
sequence share an output directory, so a task never removes the directory's temporaries wholesale
(the plain run does, at its start): it removes only those of its own frames (left by an earlier,
killed attempt), and the driver sweeps the rest before launching and after the last task.
"""

from __future__ import annotations

import argparse
import io
import os
import re
import sys
from contextlib import ExitStack, redirect_stderr, redirect_stdout
from pathlib import Path

__all__ = ["add_dataset_arguments", "maybe_run_dataset", "floxels_task", "remove_temps", "common_options"]

# run options that a task sets itself (per sequence / per task) or that belong to the driver
_DRIVER_KEYS = {"command", "func", "input", "out", "frames", "poses", "calib", "device", "list_methods",
                "ray", "gpus_per_task", "cpus_per_task", "max_tasks", "task_frames", "retries", "sequences"}


def add_dataset_arguments(p: argparse.ArgumentParser) -> None:
    import textwrap

    g = p.add_argument_group("datasets and clusters", textwrap.fill(
        "INPUT may also be a dataset: a directory holding sequences at any depth (an Argoverse 2 split "
        "of log folders, KITTI odometry with sequences/NN/velodyne and poses/NN.txt, a directory of "
        "'floxels simulate' sequences) or a text file listing sequence directories (one a line, "
        "optionally 'PATH --poses FILE --calib FILE'). OUT then mirrors the input tree. Without --ray "
        "the sequences run one after another here.", 92))
    g.add_argument("--ray", nargs="?", const="auto", metavar="auto|ADDRESS",
                   help="run as tasks on a Ray cluster (pip install 'floxels_ext[ray]'): 'auto' (the default "
                        "when the flag is bare) joins the cluster this machine belongs to or starts a local "
                        "one; ADDRESS is a head node (host:6379 or ray://host:10001)")
    g.add_argument("--gpus-per-task", type=float, metavar="G",
                   help="GPUs a task asks Ray for; fractions pack several tasks on a GPU (default: 1 when the "
                        "cluster has GPUs and --device is not cpu, else 0 = CPU tasks)")
    g.add_argument("--cpus-per-task", type=float, default=1.0, metavar="C",
                   help="CPUs a task asks Ray for (also its torch threads; default 1)")
    g.add_argument("--max-tasks", type=int, metavar="N", help="at most N tasks at once (default: as many as "
                   "the cluster's resources fit)")
    g.add_argument("--task-frames", type=int, default=192, metavar="N",
                   help="frames per task: longer sequences are cut into chunks (rounded up to a multiple of "
                        "--chunk; support scans beyond a chunk are still read); 0 = whole sequences "
                        "(default 192)")
    g.add_argument("--retries", type=int, default=3, metavar="N",
                   help="times Ray re-runs a task whose worker or node died (default 3)")
    g.add_argument("--sequences", action="append", metavar="GLOB",
                   help="only the sequences whose output sub-path matches this shell pattern (e.g. "
                        "'sequences/0[0-9]/*'); repeatable")


def common_options(args) -> dict:
    """The run options every task of the job shares (all but the per-task and driver ones)."""
    return {k: v for k, v in vars(args).items() if k not in _DRIVER_KEYS}


def remove_temps(out_dir: Path, names=None) -> int:
    """Removes the temporary files of interrupted writes in out_dir (only those of the frames
    ``names``, output names without ``.npz``, when given); a missing directory has none."""
    from floxels_ext.lidar.outputs import cleanup_temps

    if not Path(out_dir).is_dir():
        return 0
    return cleanup_temps(Path(out_dir), None if names is None else {f"{n}.npz" for n in names})


def task_job(task, common: dict, device: str | None, threads: int | None = None) -> dict:
    """The picklable description of a task that ``floxels_task`` runs."""
    return {"input": str(task.seq.path), "out": str(task.out_dir), "frames": f"{task.start}:{task.stop}",
            "names": list(task.names), "poses": str(task.seq.poses) if task.seq.poses else None,
            "calib": str(task.seq.calib) if task.seq.calib else None, "device": device, "threads": threads,
            "options": common}


def floxels_task(job: dict, quiet: bool = True) -> dict:
    """Runs one task as ``floxels run`` would; returns {rc, error, failed, log, host, pid}.

    ``quiet``: the run's messages and progress go to a buffer (its tail comes back in ``log``)."""
    import socket

    from floxels_ext.cli import CLIError, build_parser
    from floxels_ext.evaluation.seqio import SequenceFormatError

    if job.get("threads"):
        import torch

        torch.set_num_threads(int(job["threads"]))
    argv = ["run", job["input"], "--out", job["out"], "--frames", job["frames"]]
    for key in ("poses", "calib", "device"):
        if job.get(key):
            argv += [f"--{key}", job[key]]
    ns = build_parser().parse_args(argv)
    for k, v in job["options"].items():
        setattr(ns, k, v)
    ns.ray = None  # the task itself runs here
    ns.cpu_limit = job.get("threads")  # the default reader count stays within the task's CPUs
    if hasattr(ns, "verbosity") and quiet:
        ns.verbosity = -1
    out_dir = Path(job["out"])
    remove_temps(out_dir, set(job["names"]))  # an earlier attempt of this task was killed mid-write
    buf = io.StringIO()
    result = {"rc": 0, "error": None, "failed": [], "log": "", "host": socket.gethostname(), "pid": os.getpid()}
    streams = (redirect_stdout(buf), redirect_stderr(buf)) if quiet else ()
    # the run removes only its own frames' temporaries, so tasks can share out_dir
    with ExitStack() as stack:
        for s in streams:
            stack.enter_context(s)
        try:
            rc = ns.func(ns)
            result["rc"] = 0 if rc is None else int(rc)
        except (CLIError, SequenceFormatError, FileNotFoundError, NotADirectoryError, PermissionError) as e:
            result["rc"], result["error"] = 2, str(e)
    log = buf.getvalue().splitlines()
    if "failed frames:" in log:
        result["failed"] = [ln.strip() for ln in log[log.index("failed frames:") + 1:] if ln.startswith("  ")]
    result["log"] = "\n".join(log[-30:])
    return result


def _check_options(args, dataset: bool) -> None:
    from floxels_ext.cli import CLIError

    if args.ray is None:
        used = [f for f, v, default in (("--gpus-per-task", args.gpus_per_task, None),
                                        ("--max-tasks", args.max_tasks, None), ("--cpus-per-task", args.cpus_per_task, 1.0),
                                        ("--task-frames", args.task_frames, 192), ("--retries", args.retries, 3))
                if v != default]
        if used:
            raise CLIError(f"{', '.join(used)} only apply with --ray")
    if dataset and (args.poses or args.calib):
        raise CLIError("--poses/--calib name one sequence's files; a dataset's are found per sequence (KITTI "
                       "poses/NN.txt and sequences/NN/calib.txt) or given per line of a list file "
                       "('PATH --poses FILE --calib FILE')")
    if args.gpus_per_task is not None and args.gpus_per_task < 0:
        raise CLIError(f"--gpus-per-task must be >= 0, got {args.gpus_per_task}")
    if args.gpus_per_task and args.device == "cpu":
        raise CLIError("--gpus-per-task > 0 contradicts --device cpu")
    if args.cpus_per_task <= 0:
        raise CLIError(f"--cpus-per-task must be > 0, got {args.cpus_per_task}")
    if args.max_tasks is not None and args.max_tasks < 1:
        raise CLIError("--max-tasks must be >= 1")
    if args.task_frames < 0:
        raise CLIError("--task-frames must be >= 0 (0 = whole sequences)")
    if args.retries < 0:
        raise CLIError("--retries must be >= 0")


def maybe_run_dataset(args) -> int | None:
    """Runs a dataset (or one sequence through Ray); None when the plain run should handle INPUT."""
    from floxels_ext.cli import CLIError
    from floxels_ext.lidar.dataset import SequenceSpec, discover_dataset, plan_tasks

    if getattr(args, "list_methods", False) or not args.input or not args.out:
        return None
    specs = discover_dataset(args.input, args.out, args.sequences)
    _check_options(args, specs is not None)
    if specs is None:
        if args.sequences:
            raise CLIError(f"--sequences selects sequences of a dataset, but {args.input} is one sequence")
        if args.ray is None:
            return None
        specs = [SequenceSpec(Path(args.input).resolve(), Path("."),
                              Path(args.poses) if args.poses else None, Path(args.calib) if args.calib else None)]
    from floxels_ext.lidar.run_args import resolve_preset

    resolve_preset(args)  # --scans from the preset when not given
    if not 2 <= args.scans <= 13:
        raise CLIError(f"--scans must be in [2, 13], got {args.scans}")
    if args.chunk is not None and args.chunk < 1:
        raise CLIError("--chunk must be >= 1")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise CLIError(f"--out {out} exists and is not a directory")
    task_frames = args.task_frames if args.ray is not None else 0
    tasks, problems = plan_tasks(specs, out, args, task_frames=task_frames, align=args.chunk or 64)  # 64: half the run's default chunk
    if problems:
        raise CLIError(f"{len(problems)} of the {len(specs)} sequences cannot run (fix them or leave them out "
                       f"with --sequences):\n  " + "\n  ".join(problems))
    for t in tasks:  # what is left to do (the run skips written frames the same way)
        t.todo = list(t.names) if args.force else \
            [n for n in t.names if not (t.out_dir / f"{n}.npz").is_file()]
    common = common_options(args)
    if args.ray is not None:
        from floxels_ext.lidar.ray_runner import run_on_ray

        return run_on_ray(tasks, args, common, n_sequences=len(specs))
    return _run_here(tasks, args, common, n_sequences=len(specs))


def _run_here(tasks, args, common: dict, n_sequences: int) -> int:
    """One sequence after another in this process, each with its own progress bar."""
    from floxels_ext.cli import CLIError

    total = sum(len(t.names) for t in tasks)
    todo = sum(len(t.todo) for t in tasks)
    print(f"dataset {args.input}: {n_sequences} sequences, {total} frames, {total - todo} already done",
          file=sys.stderr, flush=True)
    failed: list[str] = []
    ran = 0
    for k, t in enumerate(tasks, 1):
        if not t.todo and not args.force:
            continue
        print(f"[{k}/{len(tasks)}] {t.seq.path} -> {t.out_dir}", file=sys.stderr, flush=True)
        remove_temps(t.out_dir)  # nothing else writes there now
        res = floxels_task(task_job(t, common, args.device), quiet=False)
        if res["rc"] == 2:
            if ran == 0:
                raise CLIError(res["error"])
            failed.append(f"{t.seq.path}: {res['error']}")
        elif res["rc"] != 0:
            failed.append(f"{t.seq.path}: some frames failed (listed above)")
        ran += 1
    if failed:
        print(f"dataset: {len(failed)} failure(s):\n  " + "\n  ".join(failed), file=sys.stderr)
        return 1
    print(f"dataset done: {n_sequences} sequences in {args.out}", file=sys.stderr)
    return 0
