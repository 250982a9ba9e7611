"""What an OUT_DIR holds besides the outputs this run writes (issue 45, item 10): outputs of
input frames that are gone, and outputs of other settings that a ``--force --frames`` run
leaves beside its own.

An output whose frame is no longer in the input (deleted, or renamed by a re-export) used to
stay among the others, where ``floxels eval`` scored it and ``show`` drew it as part of the
run. It is moved to ``OUT/orphaned/`` (kept, out of the run's way: a ``--self-contained``
output is still a record of what was computed) when its recorded source is gone or lies in
this input's frame directory; an output of another input written to this OUT_DIR is only
warned about.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["ORPHANS", "set_aside_orphans", "warn_mixed_settings"]

ORPHANS = "orphaned"


def _names(paths: list[str]) -> str:
    return ", ".join(paths[:3]) + (" ..." if len(paths) > 3 else "")


def set_aside_orphans(seq, out: Path, report) -> None:
    """Move ``out``'s outputs of frames that ``seq`` no longer holds to ``out/orphaned/``."""
    from floxels_ext.numpy_files import open_npz

    if not out.is_dir():
        return
    names = {f.name for f in seq.frames}
    frame_dir = os.path.realpath(seq.frames[0].path.parent)
    orphans, foreign = [], []
    for p in sorted(out.glob("*.npz")):
        if p.name.startswith(".") or p.stem in names:
            continue
        try:
            with open_npz(p) as z:
                if "flow" not in z.files or "settings" not in z.files:
                    continue  # not an output of floxels run: not ours to move
                src = str(z["source"]) if "source" in z.files else None
        except Exception:
            continue
        if src is None or not os.path.exists(src) or os.path.realpath(os.path.dirname(src)) == frame_dir:
            orphans.append(p)
        else:
            foreign.append(p.name)
    if orphans:
        dest = out / ORPHANS
        dest.mkdir(exist_ok=True)
        for p in orphans:
            try:
                os.replace(p, dest / p.name)
            except FileNotFoundError:
                pass  # moved meanwhile by another task of this sequence (engines, Ray workers)
        report(f"moved {len(orphans)} output(s) of frames no longer in the input (deleted or renamed since: "
               f"{_names([p.name for p in orphans])}) to {dest}, out of the run's outputs")
    if foreign:
        report(f"floxels: warning: {out} holds {len(foreign)} output(s) of another input ({_names(foreign)}); "
               f"floxels eval and show would take them for frames of this run")


def warn_mixed_settings(seq, out: Path, selected: range, settings: dict, report) -> None:
    """``--force --frames A:B``: a warning when outputs of frames outside A:B were written with
    other settings (the directory will mix them; ``floxels eval`` refuses such a mix)."""
    from floxels_ext.lidar.io.outputs import read_settings, settings_mismatch

    odd = []
    for k, f in enumerate(seq.frames):
        path = out / f"{f.name}.npz"
        if k in selected or not path.is_file():
            continue
        rec = read_settings(path)
        diff = settings_mismatch(rec, settings) if rec is not None else []
        if diff:
            odd.append((f.name, diff))
    if odd:
        report(f"floxels: warning: --force recomputes --frames {selected.start}:{selected.stop} only; {len(odd)} "
               f"other output(s) in {out} were written with other settings ({odd[0][0]}: "
               f"{'; '.join(odd[0][1])[:200]}), so it will mix settings, which floxels eval refuses to score as "
               f"one run: recompute them too (--force without --frames) or write to another --out")
