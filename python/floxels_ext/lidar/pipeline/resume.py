"""What each frame's output was computed from, so that a resumed ``floxels run`` recomputes the
frames whose inputs changed (issue 30, item 4), and which frames of a sequence are still to do
(:func:`resume_plan`, :func:`check_resume`).

A frame's flow depends on the scans of its window (the method's window around it, and the
next scan, whose pose gives ``ego_motion``), their poses and their times. Each output records
them as ``inputs`` (JSON)::

    {"scans": {NAME: [size, mtime_ns], ...},      # each window file's size and modification time
     "poses": {NAME: "blake2b of the 4x4", ...},   # null: the poses are in the files, or none
     "times": {NAME: seconds after the target, ...},  # null: frames evenly spaced
     "read": {"bin_columns": 3}}                   # only where a reading option is given

Sizes with modification times, not content hashes: a stat per file costs microseconds while
hashing every scan again would cost a read of the whole sequence per run; an edit, a copy
over or a fixed file changes the time (``cp -p`` of a same-size file with its old time would
not be seen). Poses and times are recorded as resolved values, so editing one line of a poses
file recomputes only the frames whose windows use that pose, and removing ``times.txt``
recomputes the frames whose offsets it set.

A reading option that changes the points read from the same files (``--bin-columns`` of
``.bin`` frames) is an input too: outputs read with another one are recomputed (issue 45: a
rerun with ``--bin-columns 3`` kept the outputs of x y z-only files misread as 4 columns).
It is recorded only when given, so records without ``read`` mean the default reading.

Outputs written before this record existed have no ``inputs``: they are kept as done (their
inputs cannot be compared), and the run says how many, pointing at ``--force``.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np

__all__ = ["window_frames", "input_records", "inputs_diff", "resume_plan", "check_resume"]


def window_frames(i: int, n: int, num_scans: int) -> range:
    """The frames whose scans frame ``i``'s output depends on: the estimator's window
    (:func:`floxels_ext.estimator.api.window_for`), widened to the neighbours the two-scan
    methods pair with (``i - 1`` at the end of a sequence, else ``i + 1``; ``i + 1`` also gives
    ``ego_motion``)."""
    from floxels_ext.estimator.api import window_for

    lo, hi = window_for(i, n, num_scans)
    return range(min(lo, max(i - 1, 0)), max(hi, min(i + 2, n)))


def _pose_digest(pose) -> str:
    return hashlib.blake2b(np.ascontiguousarray(pose, np.float64).tobytes(), digest_size=10).hexdigest()


def input_records(seq, frames, num_scans: int, poses, times_s) -> dict[int, str]:
    """``{frame: inputs JSON}`` for each of ``frames`` (indices into ``seq``): see the module doc.
    ``poses``: the (F, 4, 4) table the run uses, or None (poses inside the files, or none);
    ``times_s``: per-frame times (s), or None."""
    n = len(seq)
    need = sorted({j for i in frames for j in window_frames(i, n, num_scans)})
    stat: dict[int, list | None] = {}
    for j in need:
        try:
            st = os.stat(seq.frames[j].path)
            stat[j] = [int(st.st_size), int(st.st_mtime_ns)]
        except OSError:
            stat[j] = None
    digest = {j: _pose_digest(poses[j]) for j in need} if poses is not None else None
    read = _read_options(seq)
    out = {}
    for i in frames:
        win = window_frames(i, n, num_scans)
        names = [seq.frames[j].name for j in win]
        rec = {"scans": {nm: stat[j] for nm, j in zip(names, win)},
               "poses": None if digest is None else {nm: digest[j] for nm, j in zip(names, win)},
               "times": None if times_s is None else
               {nm: round(float(times_s[j]) - float(times_s[i]), 9) for nm, j in zip(names, win)}}
        if read:
            rec["read"] = read
        out[i] = json.dumps(rec, sort_keys=True)
    return out


def _read_options(seq) -> dict:
    """The reading options given that change the points read from ``seq``'s files."""
    if seq.bin_columns is not None and seq.frames and seq.frames[0].path.suffix.lower() == ".bin":
        return {"bin_columns": int(seq.bin_columns)}
    return {}


def inputs_diff(recorded: dict, current: dict) -> str | None:
    """None when the two records match, else what changed (for the message)."""
    if recorded == current:
        return None
    ra, rb = recorded.get("read") or {}, current.get("read") or {}
    if ra != rb:
        def said(r):
            return f"--bin-columns {r['bin_columns']}" if "bin_columns" in r else "the column count from the size"

        return f"its scans are read with {said(rb)} now ({said(ra)} then)"
    rs, cs = recorded.get("scans") or {}, current.get("scans") or {}
    if set(rs) != set(cs):
        return "its window holds other frames now"
    changed = [nm for nm in cs if rs[nm] != cs[nm]]
    if changed:
        return f"{', '.join(changed[:3])}{' ...' if len(changed) > 3 else ''} changed"
    for key, what in (("poses", "poses"), ("times", "frame times")):
        a, b = recorded.get(key), current.get(key)
        if a != b:
            if a is None or b is None:
                return f"{what} {'now given' if a is None else 'no longer given'}"
            return f"the {what} of {', '.join(nm for nm in b if a.get(nm) != b[nm])[:60]} changed"
    return "its inputs changed"


def resume_plan(seq, selected: list[int], out, args, options: dict, settings, pose_mode: str, poses, report,
                resume_report=None, sweep: bool = True) -> dict:
    """What a sequence's run writes and what is already done, the same for ``floxels run SEQ``
    and each sequence of a dataset: the run's settings, each selected frame's output path, the
    frames' timestamps and times (s), what each output depends on (its window's files, poses,
    times: :func:`input_records`) and the frames still to do (:func:`check_resume`, which
    reports to ``resume_report``, default ``report``). ``sweep``: first set aside the outputs of
    frames no longer in the input (``out_dir.py``). Keys: settings, out_path, stamps, times_s,
    times_source, inputs, todo."""
    from floxels_ext.lidar.pipeline.out_dir import set_aside_orphans, warn_mixed_settings
    from floxels_ext.lidar.pipeline.run_args import parse_frame_range
    from floxels_ext.lidar.pipeline.run_inputs import frame_times, run_settings

    if sweep:
        set_aside_orphans(seq, Path(out), report)
    settings_ = run_settings(args, options, settings, pose_mode, seq)
    out_path = {i: out / f"{seq.frames[i].name}.npz" for i in selected}
    # per-frame times in seconds where the input names them (AV2 sweeps: ns timestamps); the
    # pipeline passes them to methods whose estimate_sequence takes ``times``
    stamps = [f.timestamp_ns for f in seq.frames]
    times_s, times_source = frame_times(seq, stamps, report)
    inputs = input_records(seq, selected, args.scans, poses if pose_mode == "table" else None, times_s)
    todo = check_resume(out_path, selected, settings_, args.force, inputs=inputs, report=resume_report or report)
    if args.force and args.frames:
        warn_mixed_settings(seq, Path(out), range(*parse_frame_range(args.frames, len(seq))), settings_, report)
    return {"settings": settings_, "out_path": out_path, "stamps": stamps, "times_s": times_s,
            "times_source": times_source, "inputs": inputs, "todo": todo}


def check_resume(out_path: dict, selected: list[int], settings: dict, force: bool, inputs: dict | None = None,
                 report=None) -> list[int]:
    """Frames to estimate: those without an output, those whose output cannot be read
    (truncated by a crash, not an output), those whose inputs changed since they were written
    (``inputs``: ``{frame: JSON record}`` of :func:`input_records`), and
    (with --force) all. An output written with other settings (method, options, preprocessing,
    poses source, ...) stops the run (CLIError) unless --force. Outputs of earlier versions
    carry no input record: they count as done, and ``report`` says so."""
    from floxels_ext.errors import CLIError
    from floxels_ext.lidar.io.outputs import read_resume_record, settings_mismatch

    if force:
        return list(selected)
    todo, clash = [], None
    unreadable, changed, legacy = [], [], []
    for i in selected:
        if not out_path[i].is_file():
            todo.append(i)
            continue
        rec = read_resume_record(out_path[i])
        if rec is None:  # unreadable (e.g. truncated by a crash of the machine): recompute it
            todo.append(i)
            unreadable.append(i)
            continue
        diff = settings_mismatch(rec["settings"], settings)
        if diff and clash is None:
            clash = (out_path[i], diff)
        if inputs is None or i not in inputs:
            continue
        if rec["inputs"] is None:
            legacy.append(i)
            continue
        why = inputs_diff(rec["inputs"], json.loads(inputs[i]))
        if why is not None:
            todo.append(i)
            changed.append((i, why))
    if clash is not None:
        raise CLIError(f"{clash[0]} was written with other settings ({'; '.join(clash[1])}); "
                       f"use --force to recompute, or another --out{_paper_hint(clash[0], settings)}")
    if report is not None:
        def names(frames):
            return ", ".join(out_path[i].name for i in frames[:3]) + (" ..." if len(frames) > 3 else "")

        if unreadable:
            report(f"recomputing {len(unreadable)} output(s) that cannot be read (truncated or not an output of "
                   f"floxels run): {names(unreadable)}")
        if changed:
            i, why = changed[0]
            report(f"recomputing {len(changed)} frame(s) whose inputs changed since they were written (their "
                   f"window's scans, poses or times), e.g. {out_path[i].name}: {why}")
        if legacy:
            report(f"floxels: warning: {len(legacy)} output(s) were written by an earlier version without a record "
                   f"of their inputs ({names(legacy)}): kept as done; a change of their scans, poses or times "
                   f"since then is not detected (--force recomputes them)")
    return sorted(todo)


def _paper_hint(path, settings: dict) -> str:
    """A hint for outputs of the paper preset resumed with the accurate one: ``floxels run``'s
    default before issue 42 made accurate its default."""
    from floxels_ext.lidar.io.outputs import read_resume_record

    rec = read_resume_record(path)
    old = ((rec or {}).get("settings") or {}).get("options") or {}
    new = settings.get("options") or {}
    if settings.get("method") == "floxels" and new.get("rigid_refine") and not old.get("rigid_refine"):
        return (" (floxels run's default preset is accurate; --preset paper continues outputs of the paper's "
                "settings, the default of earlier versions)")
    return ""
