"""A dataset for ``floxels run``: the sequences under a root (or in a list file), where each one's
output goes, and how a sequence is cut into tasks.

``floxels run DATASET --out OUT`` accepts, besides one sequence directory:

* a directory tree holding sequences at any depth: an Argoverse 2 split
  (``<log_id>/sensors/lidar``), KITTI odometry (``sequences/NN/velodyne`` with the poses in
  ``poses/NN.txt`` and ``sequences/NN/calib.txt`` paired automatically), a directory of
  ``floxels simulate`` sequences, or any directories of frame files;
* a text file listing sequence directories, one a line (``#`` comments; relative paths are
  relative to the file), optionally followed by ``--poses FILE`` and ``--calib FILE`` for that
  sequence.

Directories of ``floxels run`` outputs (``.npz`` files holding ``flow`` and ``settings``) are
never taken for sequences, and symbolic links that lead back up the tree are followed once. A
directory that holds frame files *and* sequences below it (two stray frames at a dataset root)
is refused, naming both: it used to become one short sequence that hid every sequence below it.

A sequence's output goes to ``OUT/<its path relative to the root>``, so the output tree mirrors
the input tree. A task is a contiguous range of a sequence's frames, run as ``floxels run SEQ
--frames A:B``: ``--frames`` keeps the neighbours outside the range as support scans, so every
window is exactly the one the run over the whole sequence uses.
"""

from __future__ import annotations

import fnmatch
import os
import shlex
from dataclasses import dataclass, field, replace
from pathlib import Path

__all__ = ["common_options", "SequenceSpec", "Task", "discover_dataset", "is_sequence_dir", "plan_tasks", "split_task",
           "task_size", "written_names"]

# run options that a task sets itself (per sequence / per task) or that belong to the driver
_DRIVER_KEYS = {"command", "func", "input", "out", "frames", "poses", "calib", "device", "list_methods",
                "ray", "gpus_per_task", "cpus_per_task", "max_tasks", "task_frames", "retries", "sequences",
                "keep_workers", "engines", "mps"}


def common_options(args) -> dict:
    """The run options every task of the job shares (all but the per-task and driver ones)."""
    return {k: v for k, v in vars(args).items() if k not in _DRIVER_KEYS}


@dataclass
class SequenceSpec:
    path: Path                   # the directory ``floxels run`` reads
    rel: Path                    # output sub-directory (mirrors the input tree); "." = OUT itself
    poses: Path | None = None    # per-sequence --poses / --calib (KITTI pairing or list file)
    calib: Path | None = None


@dataclass
class Task:
    """Frames [start, stop) of one sequence; ``names`` are their output stems, ``todo`` those to
    estimate (not written yet, or written from inputs that changed since: the resume check)."""

    seq: SequenceSpec
    out_dir: Path
    start: int
    stop: int
    names: list[str]
    todo: list[str] = field(default_factory=list)
    frame_paths: list[str] = field(default_factory=list)   # input files, for failure reports
    summary: Path | None = None  # where its run_summary.json goes (--summary); None: in out_dir
    # the frames [start, stop) the run selects of this sequence (--frames), of which the task is
    # a part; None: all of them
    selection: tuple[int, int] | None = None
    # the sequence as ``discover_input`` listed it when the task was made here (``floxels run
    # SEQ``), so that opening it does not list it again; None: opened from ``seq``
    found: object = field(default=None, repr=False, compare=False)
    # the run has said the sequence's start lines (``floxels run SEQ`` cut into tasks for its
    # engines): the engine that opens the task says none of them again
    said: bool = False

    @property
    def label(self) -> str:
        return f"{self.seq.path} frames {self.start}:{self.stop}"


def _lidar_suffixes() -> tuple[str, ...]:
    from floxels_ext.lidar.io.readers import SUFFIXES

    return tuple(SUFFIXES)


def is_sequence_dir(d: Path) -> bool:
    """Whether ``floxels run`` would read ``d`` as one sequence (AV2 log or a directory of frames,
    not of ``floxels run`` outputs)."""
    if (d / "sensors" / "lidar").is_dir():
        return True
    return bool(_frame_files(d)) and not _is_run_output(d)


def _frame_files(d: Path) -> list[str]:
    """The names of ``d``'s lidar frame files (broken links included: they are frames that fail)."""
    suffixes = _lidar_suffixes()
    try:
        # os.path.splitext, not Path(name).suffix: a dataset's listing visits every frame name
        # (12,000 for 80 sequences) before its first task is handed out
        return sorted(e.name for e in os.scandir(d) if not e.name.startswith(".")
                      and os.path.splitext(e.name)[1].lower() in suffixes and (e.is_file() or e.is_symlink()))
    except OSError:
        return []


def _is_run_output(d: Path) -> bool:
    """Whether ``d`` holds ``floxels run`` outputs (a summary, or .npz frames with a flow and
    settings) rather than input frames."""
    if (d / "run_summary.json").is_file():
        return True
    first = next((n for n in _frame_files(d) if n.lower().endswith(".npz")), None)
    if first is None:
        return False
    from floxels_ext.numpy_files import open_npz

    try:
        with open_npz(d / first) as z:
            return "flow" in z.files and "settings" in z.files
    except Exception:  # not readable as .npz: an input frame that will fail with its reason
        return False


def _kitti_pairing(d: Path) -> tuple[Path | None, Path | None]:
    """KITTI odometry ``.../sequences/NN/velodyne``: (``.../poses/NN.txt``, ``.../sequences/NN/calib.txt``)
    when those files exist."""
    if d.name != "velodyne" or d.parent.parent.name != "sequences":
        return None, None
    nn = d.parent.name
    poses = d.parent.parent.parent / "poses" / f"{nn}.txt"
    calib = d.parent / "calib.txt"
    return (poses if poses.is_file() else None), (calib if calib.is_file() else None)


def _walk(root: Path, exclude: Path | None) -> tuple[list[Path], list[tuple[Path, list[Path]]]]:
    """(sequence directories under ``root`` at any depth, [(a directory holding frame files,
    the sequences below it)]: the ambiguous ones). A sequence's sub-directories are searched too
    (an AV2 log's ``sensors/lidar`` excepted), so that stray frame files never hide sequences."""
    found: list[Path] = []
    mixed: list[tuple[Path, list[Path]]] = []
    seen: set[str] = set()

    def subdirs(d: Path) -> list[Path]:
        try:
            return [Path(p) for p in sorted(e.path for e in os.scandir(d) if e.is_dir() and not e.name.startswith("."))]
        except OSError:
            return []

    def visit(d: Path, depth: int) -> list[Path]:
        if exclude is not None and (d == exclude or exclude in d.parents):
            return []  # never read our own output tree as input
        real = os.path.realpath(d)
        if real in seen:  # a link back up the tree (or to a place seen): once
            return []
        seen.add(real)
        if depth > 0 and (d / "sensors" / "lidar").is_dir():
            found.append(d)
            return [d]
        below = [q for s in subdirs(d) for q in visit(s, depth + 1)]
        if depth > 0 and is_sequence_dir(d):
            if below:
                mixed.append((d, below))
            found.append(d)
            return [d, *below]
        return below

    visit(root, 0)
    return sorted(found), mixed


def _mixed_error(d: Path, below: list[Path], root: Path):
    from floxels_ext.errors import CLIError

    files = _frame_files(d)
    rel = [str(q.relative_to(root)) if root in q.parents else str(q) for q in below]
    return CLIError(f"{d} holds {len(files)} frame file(s) ({', '.join(files[:3])}{' ...' if len(files) > 3 else ''}) "
                    f"and {len(below)} sequence(s) in its sub-directories ({', '.join(rel[:3])}"
                    f"{' ...' if len(rel) > 3 else ''}): it is not clear whether it is one sequence or holds "
                    f"sequences. Move the stray frame files away (then its sub-directories are the sequences), "
                    f"or give one sequence directory as INPUT")


def _read_list(list_file: Path) -> list[SequenceSpec]:
    from floxels_ext.errors import CLIError

    specs = []
    base = list_file.parent
    try:
        lines = list_file.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as e:
        raise CLIError(f"cannot read the sequence list {list_file}: {e}") from None
    for no, line in enumerate(lines, 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        try:
            words = shlex.split(line)
        except ValueError as e:
            raise CLIError(f"{list_file}:{no}: {e}") from None
        path, opts, rest = words[0], {}, words[1:]
        while rest:
            key = rest.pop(0)
            if key not in ("--poses", "--calib") or not rest:
                raise CLIError(f"{list_file}:{no}: expected 'PATH [--poses FILE] [--calib FILE]', got {line!r}")
            opts[key[2:]] = (base / rest.pop(0)).resolve()
        d = (base / path).resolve()
        if not d.is_dir() or not is_sequence_dir(d):
            what = "does not exist" if not d.exists() else "is not a sequence directory (no lidar frames, no sensors/lidar)"
            raise CLIError(f"{list_file}:{no}: {d} {what}")
        for key, p in opts.items():
            if not p.is_file():
                raise CLIError(f"{list_file}:{no}: --{key} {p} does not exist")
        poses, calib = _kitti_pairing(d)
        specs.append(SequenceSpec(d, Path("."), opts.get("poses", poses), opts.get("calib", calib)))
    if not specs:
        raise CLIError(f"the sequence list {list_file} names no sequence")
    under = all(base.resolve() in s.path.parents for s in specs)
    common = base.resolve() if under else Path(os.path.commonpath([str(s.path) for s in specs]))
    for s in specs:
        rel = s.path.relative_to(common) if s.path != common else Path(s.path.name)
        s.rel = rel if str(rel) != "." else Path(s.path.name)
    return specs


def discover_dataset(input_path, out=None, patterns: list[str] | None = None) -> list[SequenceSpec] | None:
    """The sequences of a dataset root or list file, sorted by output path; None when INPUT is
    one sequence (the plain ``floxels run`` reads it). ``patterns`` (shell globs on the output
    sub-path, e.g. ``sequences/0[0-5]/*``) select sequences. Raises CLIError when INPUT holds none."""
    from floxels_ext.errors import CLIError

    root = Path(input_path)
    if not root.exists():
        return None  # the plain run reports a missing INPUT
    if root.is_file():
        if root.suffix.lower() in _lidar_suffixes():
            return None  # one frame file: the plain run explains that INPUT must be a directory
        specs = _read_list(root)
    else:
        exclude = Path(out).resolve() if out else None
        if (root / "sensors" / "lidar").is_dir():
            return None  # an AV2 log
        dirs, mixed = _walk(root.resolve(), exclude)
        if _frame_files(root):  # frames at the root: one sequence, unless sequences lie below too
            if dirs:
                raise _mixed_error(root, dirs, root.resolve())
            return None
        if mixed:
            raise _mixed_error(*mixed[0], root.resolve())
        if not dirs:
            raise CLIError(f"{root} holds no lidar frames and no sequences in its sub-directories (at any depth: "
                           f"AV2 <log>/sensors/lidar, KITTI sequences/NN/velodyne, directories of frame files; "
                           f"directories of floxels run outputs are not inputs)")
        specs = []
        for d in dirs:
            poses, calib = _kitti_pairing(d)
            specs.append(SequenceSpec(d, d.relative_to(root.resolve()), poses, calib))
    seen: dict[Path, Path] = {}
    for s in specs:
        if s.rel in seen:
            raise CLIError(f"{seen[s.rel]} and {s.path} would write to the same output directory {s.rel}")
        seen[s.rel] = s.path
    if patterns:
        specs = [s for s in specs if any(fnmatch.fnmatchcase(s.rel.as_posix(), p) for p in patterns)]
        if not specs:
            raise CLIError(f"--sequences {' '.join(patterns)} selects none of the sequences of {root}")
    return sorted(specs, key=lambda s: s.rel.as_posix())


def plan_tasks(specs: list[SequenceSpec], out: Path, args, *, task_frames: int, align: int = 1
               ) -> tuple[list[Task], list[str]]:
    """Lists every sequence's frames (as ``floxels run`` will) and cuts them into tasks of at most
    ``task_frames`` frames (0: whole sequences), starting at multiples of ``align`` (the run's
    ``--chunk``, so tasks batch their targets exactly like the run over the whole sequence).
    Returns (tasks, problems): a problem names a sequence that cannot run and why."""
    from floxels_ext.lidar.io import MissingDependencyError
    from floxels_ext.lidar.io.poses import PoseFormatError
    from floxels_ext.lidar.io.sources import InputError, discover_input
    from floxels_ext.lidar.pipeline.run_args import parse_frame_range

    tasks: list[Task] = []
    problems: list[str] = []
    size = task_size(task_frames, align)
    for s in specs:
        try:
            seq = discover_input(s.path, poses_file=s.poses, calib=s.calib, bin_columns=args.bin_columns,
                                 ext=args.ext, points_frame=args.points_frame)
        except (InputError, PoseFormatError, MissingDependencyError) as e:
            problems.append(str(e))
            continue
        n = len(seq)
        if n < 2:
            problems.append(f"{s.path} holds {n} frame; scene flow needs at least 2")
            continue
        if seq.kind == "files" and seq.poses is None and not (args.no_ego_motion or args.odometry) \
                and seq.frames[0].path.suffix.lower() != ".npz":
            problems.append(f"{s.path}: no poses for ego-motion compensation (KITTI: poses/NN.txt next to "
                            f"sequences/; a list file: 'PATH --poses FILE'; or --odometry kiss-icp / --no-ego-motion)")
            continue
        start, stop = parse_frame_range(args.frames, n)
        out_dir = out / s.rel
        step = size or (stop - start)
        if args.odometry:  # one task per sequence: KISS-ICP runs over the whole sequence once
            step = stop - start
        # cut every `step` frames from the first selected one, where the run's own batches start
        for a, b in _cuts(start, stop, step):
            tasks.append(Task(s, out_dir, a, b, [f.name for f in seq.frames[a:b]],
                              frame_paths=[str(f.path) for f in seq.frames[a:b]], selection=(start, stop)))
    return tasks, problems


def written_names(d: Path) -> set[str]:
    """The frame names with an output file ``NAME.npz`` in ``d`` (a link counts when it leads to
    a file, as ``Path.is_file``); none when ``d`` cannot be listed (not made yet). One listing a
    directory, not a stat a frame: the driver asks for every frame of a dataset."""
    try:
        with os.scandir(d) as it:
            return {e.name[:-4] for e in it if e.name.endswith(".npz") and e.is_file()}
    except OSError:
        return set()


def task_size(task_frames: int, align: int) -> int:
    """``task_frames`` rounded up to a multiple of ``align`` (0: whole sequences)."""
    return 0 if task_frames <= 0 else -(-task_frames // align) * align


# A run of few frames on local engines (``--engines N``) gets at least this many tasks an engine:
# 768 frames in tasks of 128 left two of four engines idle for the last third of the run (6
# tasks: two engines ran two, two ran one; bench/RESULTS.md, tools/engine_timeline.py).
TASKS_PER_ENGINE = 3


def balanced_task_size(todo_frames: int, engines: int, size: int, align: int) -> int:
    """Frames a task of a run with ``todo_frames`` to do on ``engines`` local engines: ``size``
    (the run's, a multiple of ``align``; 0: whole sequences), or less, so that every engine gets
    ``TASKS_PER_ENGINE`` tasks where tasks of ``align`` frames or more allow it. Never below
    ``align`` (the run's chunk: each task is one method call of whole chunks) nor above ``size``."""
    if size <= 0 or engines <= 1 or todo_frames <= 0:
        return size
    want = task_size(-(-todo_frames // (TASKS_PER_ENGINE * engines)), align)
    return max(min(align, size), min(size, want))


def _cuts(start: int, stop: int, step: int) -> list[tuple[int, int]]:
    cuts = [*range(start, stop, step or stop - start), stop]
    return list(zip(cuts[:-1], cuts[1:]))


def split_task(task: Task, size: int) -> list[Task]:
    """``task`` (``floxels run SEQ``'s, its sequence listed: ``found``) cut into tasks of
    ``size`` frames from its first one, as :func:`plan_tasks` cuts a dataset's sequences;
    each notes that the run has said its start lines (``said``)."""
    return [_part(task, a, b, todo=[], said=True, selection=task.selection or (task.start, task.stop))
            for a, b in _cuts(task.start, task.stop, size)]


def _part(task: Task, a: int, b: int, **changes) -> Task:
    """``task``'s frames [a, b) as a task of their own (names and input paths cut alike)."""
    k0 = task.start
    return replace(task, start=a, stop=b, names=task.names[a - k0:b - k0],
                   frame_paths=task.frame_paths[a - k0:b - k0], **changes)


def halve_task(task: Task, align: int, min_frames: int, first: float | None = None) -> tuple[Task, Task] | None:
    """``task`` cut in two at the cut nearest its middle (``first``: nearest ``first`` frames
    from its start) that is a multiple of ``align`` from the selection's first frame (1: any
    frame; every window and chunk anchor stays the run's wherever the cut,
    ``layout.plan_chunks``), each part at least ``min_frames`` frames with some left to do; None
    where no such cut exists. The Ray driver cuts the tasks it hands out last, so that the
    workers end together (a job's tail: whole 150-frame sequences ended up to ~1.3 s apart on 4
    GPUs; ``ray_tail``)."""
    a0 = (task.selection or (task.start, task.stop))[0]
    m = max(1, min_frames)
    cuts = [c for c in range(task.start + m, task.stop - m + 1) if (c - a0) % max(1, align) == 0]
    if not cuts:
        return None
    target = task.start + task.stop if first is None else 2 * task.start + 2 * first  # (twice the cut)
    cut = min(cuts, key=lambda c: (abs(2 * c - target), c))
    todo = set(task.todo)
    parts = [_part(task, a, b) for a, b in ((task.start, cut), (cut, task.stop))]
    for p in parts:
        p.todo = [n for n in p.names if n in todo]
    return None if not (parts[0].todo and parts[1].todo) else (parts[0], parts[1])
