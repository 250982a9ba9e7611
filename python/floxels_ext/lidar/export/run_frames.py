"""What every export format reads of a ``floxels run`` OUT_DIR: its sequences, what each frame's
output says about itself (read without its arrays, so a whole split is checked before anything
is written), and its flow turned into the convention of the Argoverse 2 challenge and of the
training frameworks that follow it.

``floxels run`` writes per frame (``lidar/io/outputs.py``) the flow of every point in the
frame's own coordinates, ego-motion compensated (static points 0), in metres per frame period
(the median step of the frame times when the run had them), and ``ego_motion``, the rigid
transform from the frame's coordinates to the next frame's. The Argoverse 2 scene flow
challenge and OpenSceneFlow's files store instead, for each point ``p`` of sweep t, where it is
at sweep t+1 *in sweep t+1's coordinates*, as a displacement from ``p``:
``flow = E (p + s f) - p`` with ``E`` = ego_motion and ``s`` = (time to the next sweep) / (frame
period): the sweeps of a 10 Hz log are not exactly one period apart (the shared pair's: 100.196 ms).
:func:`displacement_to_next` computes that in float64.
"""

from __future__ import annotations

import json
import statistics
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["ExportError", "FrameInfo", "RunSequence", "find_sequences", "read_frame_info", "sequence_infos",
           "displacement_to_next", "MAX_DEPTH"]

MAX_DEPTH = 4  # a dataset run mirrors its input tree: KITTI's dataset/sequences/NN/velodyne is depth 3


class ExportError(ValueError):
    """The run cannot be exported in the asked format (the message says why and names the file)."""


@dataclass
class FrameInfo:
    """One output of ``floxels run``, as far as its small fields tell (no points read)."""

    path: Path
    name: str                       # output stem (the frame file's stem)
    rows: int                       # points of the frame file (rows of 'flow')
    timestamp_ns: int | None        # the sweep's time (Argoverse 2), when the input named it
    source: str | None              # the frame file the run read
    settings: dict                  # what the run computed it with (ego_motion source, poses, method)
    points_frame: str               # "native" (each frame's own coordinates) or "world" (one frame)
    has_ego_motion: bool
    next_name: str | None = None    # the frame after it in the input sequence (None: the last one)
    step: float | None = None       # time to that frame (unit of the run's frame times; None: none)


@dataclass
class RunSequence:
    """The outputs of one input sequence: a plain run's OUT_DIR, or one sub-directory of a
    dataset run (which mirrors its input tree)."""

    out_dir: Path
    rel: str                        # path relative to RUN ("." for a plain run)
    outputs: list[Path] = field(default_factory=list)   # natural order


def _outputs(d: Path) -> list[Path]:
    from floxels_ext.lidar.io.readers import natural_key

    return sorted((p for p in d.glob("*.npz") if p.is_file() and not p.name.startswith(".")),
                  key=lambda p: natural_key(p.name))


def find_sequences(run_dir) -> list[RunSequence]:
    """The sequences of RUN: RUN itself when it holds outputs, else its sub-directories that do
    (at most ``MAX_DEPTH`` levels down, sorted)."""
    root = Path(run_dir)
    if not root.is_dir():
        raise ExportError(f"RUN {root} is not a directory" if root.exists() else f"RUN {root} does not exist")
    own = _outputs(root)
    if own:
        return [RunSequence(root, ".", own)]
    found = []
    level = [root]
    for _ in range(MAX_DEPTH):
        nxt = []
        for d in level:
            for sub in sorted(p for p in d.iterdir() if p.is_dir() and not p.name.startswith(".")):
                outs = _outputs(sub)
                if outs:
                    found.append(RunSequence(sub, sub.relative_to(root).as_posix(), outs))
                else:
                    nxt.append(sub)
        level = nxt
    if not found:
        raise ExportError(f"RUN {root} holds no outputs of 'floxels run' (NAME.npz files), neither itself nor in "
                          f"sub-directories up to {MAX_DEPTH} levels down")
    return found


def _flow_rows(z, path: Path) -> int:
    """Rows of 'flow' from its .npy header (the array itself is not read)."""
    with z.zip.open("flow.npy") as fh:
        version = np.lib.format.read_magic(fh)
        read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
        shape, _, _ = read(fh)
    if len(shape) != 2 or shape[1] != 3:
        raise ExportError(f"{path}: 'flow' must be (N, 3), got {shape}")
    return int(shape[0])


def read_frame_info(path) -> FrameInfo:
    """A :class:`FrameInfo` of one output; :class:`ExportError` when it is not an output of
    ``floxels run`` (or cannot be read)."""
    from floxels_ext.lidar.io.readers import natural_key
    from floxels_ext.numpy_files import open_npz

    path = Path(path)
    try:
        with open_npz(path) as z:
            keys = set(z.files)
            if "flow" not in keys or "settings" not in keys:
                raise ExportError(f"{path}: not an output of 'floxels run' (keys {sorted(keys)}; 'flow' and "
                                  f"'settings' expected)")
            rows = _flow_rows(z, path)
            small = {k: z[k] for k in ("timestamp_ns", "source", "settings", "points_frame", "inputs") if k in keys}
    except ExportError:
        raise
    except Exception as e:  # zip and npy errors come in many types
        raise ExportError(f"{path}: cannot read as an output of 'floxels run' ({e})") from None
    try:
        settings = json.loads(str(small["settings"]))
        record = json.loads(str(small["inputs"])) if "inputs" in small else None
    except ValueError as e:
        raise ExportError(f"{path}: its 'settings' or 'inputs' record is not valid JSON ({e})") from None
    info = FrameInfo(path=path, name=path.stem, rows=rows,
                     timestamp_ns=int(small["timestamp_ns"]) if "timestamp_ns" in small else None,
                     source=str(small["source"]) if "source" in small else None, settings=settings,
                     points_frame=str(small.get("points_frame", "native")), has_ego_motion="ego_motion" in keys)
    if isinstance(record, dict) and isinstance(record.get("scans"), dict):
        # the record names the scans of the frame's window, which always includes the next frame
        # (lidar/pipeline/resume.py: window_frames); their times, when the run had times
        later = [n for n in record["scans"] if natural_key(n) > natural_key(info.name)]
        if later:
            info.next_name = min(later, key=natural_key)
            times = record.get("times")
            if isinstance(times, dict) and info.next_name in times and info.name in times:
                info.step = float(times[info.next_name]) - float(times[info.name])
    return info


def sequence_infos(seq: RunSequence) -> tuple[list[FrameInfo], float | None]:
    """The :class:`FrameInfo` of each output of ``seq`` and the sequence's frame period (the
    median step of its frame times, as ``floxels run`` took it; None when it had no times).
    Outputs written before the runs recorded their inputs name no next frame: the next output
    is taken, and the step from both sweeps' timestamps."""
    infos = [read_frame_info(p) for p in seq.outputs]
    for a, b in zip(infos, infos[1:]):
        if a.next_name is None and a.step is None and a.timestamp_ns is not None and b.timestamp_ns is not None:
            a.next_name, a.step = b.name, (b.timestamp_ns - a.timestamp_ns) * 1e-9
    steps = [i.step for i in infos if i.step is not None and i.step > 0]
    return infos, (statistics.median(steps) if steps else None)


def displacement_to_next(points: np.ndarray, flow: np.ndarray, ego_motion: np.ndarray | None,
                         scale: float = 1.0) -> np.ndarray:
    """(N, 3) float64 ``E (p + scale * f) - p``: where each point is at the next frame, in the
    next frame's coordinates, minus where it is (module docstring). ``ego_motion`` None: both
    frames share one coordinate frame (a run over world-frame points)."""
    p = np.asarray(points, np.float64)
    q = p + scale * np.asarray(flow, np.float64)
    if ego_motion is not None:
        E = np.asarray(ego_motion, np.float64)
        q = q @ E[:3, :3].T + E[:3, 3]
    return q - p
