"""``floxels run``'s arguments checked before any data is read (every mistake a CLIError,
reported as ``floxels: error: ...``), and how many readers and writers to use. Which frames are
still to do (the resume) is ``resume.py``'s."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

__all__ = ["parse_options", "parse_frame_range", "require_input_and_out", "check_args", "method_options",
           "preprocess_settings", "apply_cpu_default", "check_out_dir", "host_cores", "reader_plan"]


def parse_options(items: list[str], max_iters: int | None, config: type | None) -> dict:
    """``--option KEY=VALUE`` items as typed values: parsed for the field's type of the method's
    ``config`` dataclass (bools from true/false/yes/no/on/off/1/0, tuples from a,b); JSON for
    a method without one."""
    from floxels_ext.errors import CLIError
    from floxels_ext.estimator.config_fields import parse_option_value

    opts: dict = {}
    for item in items:
        key, sep, val = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise CLIError(f"--option expects KEY=VALUE, got {item!r}")
        if config is not None:
            try:
                opts[key] = parse_option_value(config, key, val)
            except (TypeError, ValueError) as e:
                raise CLIError(f"bad --option {item!r}: {e}") from None
            continue
        try:
            opts[key] = json.loads(val)
        except json.JSONDecodeError:
            opts[key] = val  # a bare string such as reg_scale=paper
        if isinstance(opts[key], list):
            opts[key] = tuple(opts[key])
    if max_iters is not None:
        opts["max_iters"] = max_iters
    return opts


def parse_frame_range(text: str | None, n: int) -> tuple[int, int]:
    """``--frames`` (A:B, A:, :B or A; Python slice semantics) as a [start, stop) range of n frames."""
    from floxels_ext.errors import CLIError

    if not text:
        return 0, n
    try:
        if ":" in text:
            a, b = text.split(":", 1)
            sl = slice(int(a) if a.strip() else None, int(b) if b.strip() else None)
        else:
            k = int(text)
            sl = slice(k, k + 1 if k != -1 else None)
    except ValueError:
        raise CLIError(f"--frames expects A:B, A:, :B or A (integers), got {text!r}") from None
    start, stop, _ = sl.indices(n)
    if stop <= start:
        raise CLIError(f"--frames {text} selects no frame of the {n}")
    return start, stop


def preset_name(args) -> str:
    """The preset a run uses, as named (unchecked): ``--preset``, or floxels run's default,
    ``accurate`` for Floxels (issue 42), ``paper`` (none) for other methods."""
    name = getattr(args, "preset", None)
    if name is None:
        return "accurate" if getattr(args, "method", "floxels") == "floxels" else "paper"
    return name


def resolve_preset(args) -> dict:
    """``--preset``'s Floxels fields (besides the window) and ``args.scans`` set to the
    preset's window when ``--scans`` was not given; no ``--preset``: ``accurate`` for Floxels
    (the API keeps ``paper``), nothing for other methods. Raises CLIError for a preset with
    another method."""
    from floxels_ext.errors import CLIError
    from floxels_ext.presets import DEFAULT_NUM_SCANS, PRESETS  # (no torch: a Ray driver never needs it)

    name = preset_name(args)
    # '' is refused like any unknown name (as the API does)
    if name not in PRESETS:
        raise CLIError(f"unknown --preset {name!r}; choose from {', '.join(PRESETS)}")
    if name != "paper" and getattr(args, "method", "floxels") != "floxels":
        raise CLIError(f"--preset {name} sets Floxels options; it does not apply to --method {args.method}")
    fields = dict(PRESETS[name])
    window = fields.pop("num_scans", DEFAULT_NUM_SCANS)
    if getattr(args, "scans", None) is None:
        args.scans = window
    return fields


def require_input_and_out(args) -> None:
    """CLIError unless INPUT and --out are given."""
    from floxels_ext.errors import CLIError

    if not args.input or not args.out:
        raise CLIError("floxels run needs INPUT and --out OUT_DIR")


def check_args(args, torch):
    """Validate the plain arguments; returns (device, options). Raises CLIError."""
    from floxels_ext.errors import CLIError
    from floxels_ext.methods import available_methods

    resolve_preset(args)
    require_input_and_out(args)
    if args.method not in available_methods():
        raise CLIError(f"unknown --method {args.method!r}; available: {', '.join(available_methods())}")
    if not 2 <= args.scans <= 13:
        raise CLIError(f"--scans must be in [2, 13], got {args.scans}")
    if args.chunk is not None and args.chunk < 1:
        raise CLIError("--chunk must be >= 1")
    if args.workers is not None and args.workers < 1:
        raise CLIError("--workers must be >= 1")
    if getattr(args, "writers", None) is not None and args.writers < 1:
        raise CLIError("--writers must be >= 1")
    if not (np.isfinite(args.dynamic_threshold) and args.dynamic_threshold >= 0):
        raise CLIError(f"--dynamic-threshold must be a finite number >= 0 (m per frame), got {args.dynamic_threshold}")
    if args.calib and not args.poses:
        raise CLIError("--calib turns the camera poses of --poses into lidar poses; it needs --poses FILE")
    if args.poses and getattr(args, "odometry", None):  # one would be silently ignored (--odometry)
        raise CLIError(f"--poses FILE and --odometry {args.odometry} both give the ego-motion; give one of them")
    device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    if device not in ("cpu", "cuda") and not device.startswith("cuda:"):
        raise CLIError(f"--device must be cpu or cuda, got {device!r}")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise CLIError("--device cuda requested but no CUDA device is available")
    if args.preprocess_device == "cuda" and not torch.cuda.is_available():
        raise CLIError("--preprocess-device cuda requested but no CUDA device is available")
    return device, method_options(args)


def method_options(args) -> dict:
    """The method's options as the outputs record them (``--option``, ``--max-iters``, the
    preset, the window, the motion evidence), checked; no device needed, so the dataset driver
    compares resumes with them too. Raises CLIError."""
    from floxels_ext.errors import CLIError
    from floxels_ext.methods import available_methods, get_method

    preset_fields = resolve_preset(args)
    if args.method not in available_methods():
        raise CLIError(f"unknown --method {args.method!r}; available: {', '.join(available_methods())}")
    options = parse_options(args.option, args.max_iters, get_method(args.method).config)
    if "num_scans" in options and options["num_scans"] != args.scans:
        raise CLIError(f"--option num_scans={options['num_scans']} contradicts --scans {args.scans}; "
                       f"give the window size once, with --scans")
    raw = bool(getattr(args, "raw_flow", False))
    if args.method == "floxels":  # the baselines estimate from a (frame, next frame) pair
        # motion evidence (estimator/evidence.py): unexplained motion zeroed by default, written
        # either way; a setting like the others (options, recorded, compared on resume)
        if raw and options.get("evidence") == "zero":
            raise CLIError("--raw-flow contradicts --option evidence=zero; give one of them")
        options = {**preset_fields, "num_scans": args.scans, "evidence": "score" if raw else "zero", **options}
        from floxels_ext.estimator.config import FloxelsConfig  # fail fast on a bad option instead of after reading data
        try:
            FloxelsConfig(**options)
        except (TypeError, ValueError) as e:
            raise CLIError(f"bad --option for floxels: {e}") from None
    return options


def preprocess_settings(args):
    """The per-scan preprocessing (``Preprocess``) of the run's options; CLIError when they
    contradict each other. One definition for one sequence and a dataset."""
    from floxels_ext.errors import CLIError
    from floxels_ext.lidar.preprocess.settings import Preprocess

    try:
        return Preprocess(min_range=args.min_range, max_range=args.max_range, max_height=args.max_height,
                          remove_ground=not args.no_ground_removal, ground_cell=args.ground_cell,
                          ground_window=args.ground_window, ground_threshold=args.ground_threshold,
                          outlier_below=args.outlier_below, outlier_above=args.outlier_above)
    except ValueError as e:
        raise CLIError(str(e)) from None


def apply_cpu_default(args, device: str, report=None) -> None:
    """On the CPU, torch's threads as every command's CPU work sets them
    (:func:`floxels_ext.cpu_threads.apply_cpu_threads`), unless a Ray worker has set them to the
    CPUs it was given (``args.cpu_limit``). ``report(msg)`` says what was chosen."""
    if device == "cpu" and not getattr(args, "cpu_limit", None):
        from floxels_ext.cpu_threads import apply_cpu_threads

        apply_cpu_threads(report)


def check_out_dir(out: Path, seq) -> None:
    """``--out`` not the input, and a place that takes files (tried with a write: a read-only
    place is refused here, before any frame is read). Raises CLIError."""
    from floxels_ext.errors import CLIError
    from floxels_ext.output_paths import check_writable_dir

    if out.exists() and not out.is_dir():
        raise CLIError(f"--out {out} exists and is not a directory")
    o = out.resolve()
    frame_dir = seq.frames[0].path.parent.resolve()
    for d, what in ((seq.root.resolve(), "the input directory"), (frame_dir, "the directory of the frame files")):
        if o == d:
            raise CLIError(f"--out {out} is {what}: the outputs would be taken for input frames by the next run; "
                           f"choose another directory")
    check_writable_dir(out, "--out")


def host_cores(args) -> int:
    """The cores this run may use: the host's, or fewer where ``args.cpu_limit`` says so (set
    by a Ray task: the CPUs it was given)."""
    cores = os.cpu_count() or 1
    limit = getattr(args, "cpu_limit", None)
    return min(cores, max(1, int(limit))) if limit else cores


def reader_plan(args, device: str) -> tuple[str | None, int, int, str]:
    """(preprocessing device, None for the compiled CPU op; readers; writers; "thread" or
    "process", the kind of both).

    Cropping and ground removal run in the compiled CPU op by default: a few ms a 200k-point
    scan without the GIL, so reader threads overlap the optimiser instead of taking turns with
    its Python (bench/bench_run.py, bench/RESULTS.md; the GPU path, --preprocess-device cuda,
    launches ~30 small kernels and syncs from each thread). Readers and writers are threads
    unless ``--worker-kind process`` (measured slower on an H100 host: 26-33 frames/s against
    75-83 with threads, bench/RESULTS.md). At most 6 readers by default: on a 16-core H100 host
    6 gave 132/127 frames/s (KITTI/AV2 layout), 4 gave 119/117, 3 gave 125/109
    (bench/RESULTS.md, floxels run). ``args.cpu_limit`` (set by a Ray task: the CPUs it was
    given) caps the default worker count."""
    cores = host_cores(args)
    pre_dev = (device if device.startswith("cuda") else "cuda") if args.preprocess_device == "cuda" else None
    workers = args.workers or max(1, min(6, cores))
    kind = "thread" if args.worker_kind == "auto" else args.worker_kind
    return pre_dev, workers, args.writers or 2, kind
