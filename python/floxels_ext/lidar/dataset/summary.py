"""A sequence's ``run_summary.json``, also when several tasks (engines) ran its frames.

Each task that ends leaves a *part* (:func:`summary_part`: plain data, picklable, keyed by frame
index so that parts merge exactly); a sequence's parts are merged (:func:`merge_parts`) and
written once (:func:`write_summary`). ``floxels run SEQ`` with one engine writes the part of its
one task: the same code, the same file. With ``--engines N`` the run merges the parts of every
task of the sequence, whichever engine ran it, so the summary covers the whole run: the counts
add up, the per-frame records are the union (a support scan outside ``--frames`` that two tasks
read is counted once), the stage times are summed over the engines.
"""

from __future__ import annotations

import json
import os
import statistics
from pathlib import Path

__all__ = ["summary_part", "merge_parts", "write_summary", "summary_path", "SequenceParts", "settle_failures",
           "failure_lines"]


def _owned(job, i: int) -> bool:
    """Whether a frame that could not be read counts as one of ``job``'s failures: its own
    frames, and neighbours outside what the run selects (``--frames``: no task owns them),
    read as support scans; a neighbour that is another task's frame is that task's."""
    task = job.info["task"]
    a, b = task.selection or (0, job.n)
    return task.start <= i < task.stop or not a <= i < b


def settle_failures(job) -> None:
    """Adds the frames ``job``'s loader could not use (unreadable, empty after cropping) to its
    failures: a support scan's too, so that a run with an unreadable frame never ends as if all
    were well (:func:`_owned`)."""
    for i, msg in list(job.loader.errors.items()):
        if _owned(job, i):
            job.failed.setdefault(i, msg)


def failure_lines(job) -> list[str]:
    """One line per failed frame, naming its file."""
    out = []
    for i in sorted(job.failed):
        path = str(job.seq.frames[i].path)
        msg = job.failed[i]
        out.append(msg if msg.startswith(path) else f"{path}: {msg}")
    return out


def summary_path(task, out) -> Path:
    """Where the summary of ``task``'s sequence goes: ``--summary`` or ``OUT/run_summary.json``."""
    return Path(task.summary) if task.summary else Path(out) / "run_summary.json"


def summary_part(job, ctx, engine: int = 0) -> dict:
    """What ``job`` (a ``stream.SeqJob`` whose frames are all done) adds to its sequence's
    summary; its failures settled first (:func:`settle_failures`)."""
    settle_failures(job)
    seq, info, args = job.seq, job.info, ctx.args
    todo = set(job.todo)
    name = {i: f.name for i, f in enumerate(seq.frames)}
    loader = job.loader
    return {
        "head": {"input": str(seq.root), "out": str(info["out"]), "method": args.method, "device": ctx.device,
                 "frames": len(seq), "workers": ctx.workers, "writers": ctx.writers, "worker_kind": ctx.kind,
                 "writer_kind": ctx.kind, "preprocess_device": ctx.pre_device or "cpu",
                 "settings": json.loads(json.dumps(info["settings"], default=str))},
        "path": str(summary_path(info["task"], info["out"])),
        "selected": len(info["selected"]), "written": job.written, "skipped": info["skipped"],
        "failures": {i: (name[i], line) for i, line in zip(sorted(job.failed), failure_lines(job))},
        "nonfinite": {i: (name[i], seq.frames[i].path.name, k) for i, k in loader.nonfinite.items() if i in todo},
        "empty_crop": {i: name[i] for i in loader.empty_crop if _owned(job, i)},
        "stray": {i: name[i] for i in loader.stray if _owned(job, i)},
        "counts": {i: (name[i], c) for i, c in loader.counts.items() if i in todo},
        "times": list(job.times), "t_start": job.t_start, "t_end": job.t_end,
        "stages": {engine: ctx.stages.as_dict()}}


def merge_parts(parts: list[dict]) -> dict:
    """One part for the sequence of ``parts`` (tasks of one sequence, any engines)."""
    out = {"head": parts[0]["head"], "path": parts[0]["path"], "selected": 0, "written": 0, "skipped": 0,
           "failures": {}, "nonfinite": {}, "empty_crop": {}, "stray": {}, "counts": {}, "times": [],
           "stages": {}}
    for p in parts:
        for k in ("selected", "written", "skipped", "times"):
            out[k] += p[k]
        for k in ("failures", "nonfinite", "empty_crop", "stray", "counts"):
            for i, v in p[k].items():
                out[k].setdefault(i, v)
        for e, st in p["stages"].items():  # an engine's stage times grow over its tasks: its largest
            if sum(st.values()) >= sum(out["stages"].get(e, {}).values()):
                out["stages"][e] = st
    timed = [p for p in parts if p["times"]]
    out["t_start"] = min((p["t_start"] for p in timed), default=0.0)
    out["t_end"] = max((p["t_end"] for p in timed), default=0.0)
    return out


def _stages(per_engine: dict) -> dict:
    total: dict = {}
    for st in per_engine.values():
        for k, v in st.items():
            total[k] = total.get(k, 0.0) + v
    return {k: round(v, 4) for k, v in total.items()} if len(per_engine) > 1 else next(iter(per_engine.values()), {})


def render(part: dict, wall: float) -> dict:
    """The summary's JSON content (the format ``floxels run`` has always written)."""
    head, times, counts = part["head"], part["times"], dict(sorted(part["counts"].items()))
    failed = sorted(part["failures"])
    summary = {"input": head["input"], "out": head["out"], "method": head["method"], "device": head["device"],
               "frames": head["frames"], "selected": part["selected"], "written": part["written"],
               "skipped": part["skipped"], "failed": len(failed),
               "failures": [{"frame": part["failures"][i][0], "message": part["failures"][i][1]} for i in failed],
               "nonfinite_rows": {n: k for _, (n, _, k) in sorted(part["nonfinite"].items())},
               # frames with points but none left to optimise (counted in "failed" too)
               "no_points_after_crop": [n for _, n in sorted(part["empty_crop"].items())],
               # frames whose few far points blow up a distance transform (warned about once)
               "far_outliers": [n for _, n in sorted(part["stray"].items())],
               # per estimated frame: points kept (optimised), removed as ground, removed as
               # outliers (far below the ground / far above the sensor), cropped (or non-finite)
               "point_classes": {n: c for n, c in counts.values()},
               "outliers": sum(c["outlier"] for _, c in counts.values()),
               "wall_s": round(wall, 4),
               "frames_per_s": round(part["written"] / wall, 3) if wall > 0 and part["written"] else None,
               "s_per_frame_mean": round(statistics.mean(times), 6) if times else None,
               "s_per_frame_median": round(statistics.median(times), 6) if times else None,
               # seconds per stage; with several engines, summed over them (each its own threads)
               "stages_s": _stages(part["stages"])}
    if len(part["stages"]) > 1:
        summary["engines"] = len(part["stages"])
    if "engines_start" in part:  # a run on several engines: when they joined (dataset/engine_start.py)
        summary["engines_start"] = part["engines_start"]
    if str(head["device"]).startswith("cuda"):
        from floxels_ext.lidar.dataset.mps import sharing

        summary["mps"] = sharing()  # (--mps)
    summary.update({k: head[k] for k in ("workers", "writers", "worker_kind", "writer_kind", "preprocess_device")})
    summary["settings"] = head["settings"]
    return summary


def write_summary(part: dict, report, wall: float | None = None) -> Path | None:
    """Writes the summary of ``part`` (one task's, or a sequence's merged); returns its path
    (None when it could not be written: said as a warning). Warns first about frames with
    non-finite rows. ``wall``: the run's seconds, default from the first frame the stream took
    to the last one written."""
    nonfinite = sorted(part["nonfinite"].items())
    if nonfinite:
        report(f"floxels: warning: {len(nonfinite)} frame(s) have rows with NaN/inf coordinates (their flow "
               f"is NaN): " + ", ".join(f"{f} ({k} rows)" for _, (_, f, k) in nonfinite[:3])
               + (" ..." if len(nonfinite) > 3 else ""))
    if wall is None:
        wall = max(0.0, part["t_end"] - part["t_start"])
    path = Path(part["path"])
    try:
        from floxels_ext.output_paths import replace_atomically

        text = json.dumps(render(part, wall), indent=2) + "\n"
        replace_atomically(path.with_name(f".{path.name}.{os.getpid()}.tmp"), path, lambda t: t.write_text(text))
    except OSError as e:
        report(f"floxels: warning: cannot write the summary {path}: {e}")
        return None
    return path


class SequenceParts:
    """The parts of each sequence's tasks as they end (any engine, any order). ``run``: the
    tasks handed to the engines; ``planned``: every task of their sequences, those with
    nothing to do included (their frames count as selected and skipped, as in a run of one
    task)."""

    def __init__(self, run: list, planned: list) -> None:
        ran = {id(t) for t in run}
        self.left: dict[str, int] = {}
        self.unrun: dict[str, int] = {}
        for t in run:
            self.left[self.key(t)] = self.left.get(self.key(t), 0) + 1
        for t in planned:
            if id(t) not in ran and self.key(t) in self.left:
                self.unrun[self.key(t)] = self.unrun.get(self.key(t), 0) + len(t.names)
        self.parts: dict[str, list] = {}
        self.outcomes: dict[str, set] = {}

    def add_task(self, task) -> None:
        """One more task of a sequence already counted (a task cut in two after the start)."""
        self.left[self.key(task)] += 1

    @staticmethod
    def key(task) -> str:
        """The sequence a task belongs to: its summary's path."""
        return str(summary_path(task, task.out_dir))

    def add(self, task, outcome: str, part: dict | None) -> tuple[str, dict | None] | None:
        """A task ended; once it was its sequence's last: (the sequence's outcome, "failed" if a
        task failed, "done" if one ran, else "skipped"; its merged part, None when no task of it
        could be opened)."""
        k = self.key(task)
        self.left[k] -= 1
        self.outcomes.setdefault(k, set()).add(outcome)
        if part is not None:
            self.parts.setdefault(k, []).append(part)
        if self.left[k] > 0:
            return None
        outcomes = self.outcomes[k]
        seq_outcome = "failed" if "failed" in outcomes else "done" if "done" in outcomes else "skipped"
        if k not in self.parts:
            return seq_outcome, None
        merged = merge_parts(self.parts[k])
        merged["selected"] += self.unrun.get(k, 0)
        merged["skipped"] += self.unrun.get(k, 0)
        return seq_outcome, merged
