"""On-disk sequence format and the in-memory ``Frame`` / ``Sequence`` containers.

Format (one directory per sequence)::

    SEQ_DIR/
        000000.npz   # frame 0, written with numpy.savez_compressed
        000001.npz
        ...
        sequence.json  # optional free-form metadata (scene name, seed, lidar settings)

Each frame file holds these arrays (N = number of points of that frame):

============  ===========  =======================================================
key           shape/dtype  meaning
============  ===========  =======================================================
``points``    (N,3) f32    point positions in ONE world frame shared by the sequence
                           (ego-motion compensated: static structure has zero flow)
``pose``      (4,4) f64    optional sensor-to-world pose of this scan
``flow``      (N,3) f32    optional motion of each point to the next frame (metres)
``classes``   (N,) int     optional: 0 background, 1 car, 2 other vehicle,
                           3 pedestrian, 4 wheeled VRU
``instance``  (N,) int     optional object id, -1 for background
``ground``    (N,) bool    optional ground-point flag
``dynamic``   (N,) bool    optional moving flag (|flow| > 0.05 m per frame)
============  ===========  =======================================================

A prediction directory uses the same file names and holds at least ``flow`` in the
same point order as the ground truth. Files are written to a temporary name and
then ``os.replace``-d, so a reader never sees a half-written frame.
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from floxels_ext.numpy_files import open_npz

__all__ = [
    "CLASS_NAMES",
    "Frame",
    "Sequence",
    "SequenceFormatError",
    "frame_path",
    "list_frames",
    "write_frame",
    "read_frame",
    "load_sequence",
    "save_sequence",
]

CLASS_NAMES = ("background", "car", "other_vehicle", "pedestrian", "wheeled_vru")
FRAME_KEYS = ("points", "pose", "flow", "classes", "instance", "ground", "dynamic")
_FRAME_RE = re.compile(r"^(\d{6})\.npz$")
_META_NAME = "sequence.json"

# On-disk dtypes: compact but lossless for the value ranges we produce.
_DISK_DTYPES = {
    "points": np.float32,
    "pose": np.float64,
    "flow": np.float32,
    "classes": np.uint8,
    "instance": np.int32,
    "ground": np.bool_,
    "dynamic": np.bool_,
}
# In-memory dtypes (what read_frame returns).
_MEM_DTYPES = {**_DISK_DTYPES, "classes": np.int32}


class SequenceFormatError(ValueError):
    """A sequence directory or frame file does not follow the documented format."""


@dataclass
class Frame:
    """One lidar scan; every per-point array has the same length N."""

    points: np.ndarray
    flow: np.ndarray | None = None
    classes: np.ndarray | None = None
    instance: np.ndarray | None = None
    dynamic: np.ndarray | None = None
    ground: np.ndarray | None = None
    pose: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.points.shape[0])

    def arrays(self) -> dict[str, np.ndarray]:
        """The non-None arrays keyed by their file key."""
        return {f.name: getattr(self, f.name) for f in fields(self) if getattr(self, f.name) is not None}


@dataclass
class Sequence:
    """An ordered list of frames plus free-form metadata (scene, seed, lidar, dt)."""

    frames: list[Frame]
    meta: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i: int) -> Frame:
        return self.frames[i]

    def __iter__(self):
        return iter(self.frames)

    def save(self, directory: str | os.PathLike) -> Path:
        return save_sequence(directory, self)


def frame_path(directory: str | os.PathLike, index: int) -> Path:
    return Path(directory) / f"{index:06d}.npz"


def list_frames(directory: str | os.PathLike) -> list[Path]:
    """Frame files of ``directory`` in order; checks that their numbers are 0..n-1."""
    d = Path(directory)
    if not d.exists():
        raise SequenceFormatError(f"sequence directory {d} does not exist")
    if not d.is_dir():
        raise SequenceFormatError(f"{d} is not a directory")
    numbered = sorted((int(m.group(1)), p) for p in d.iterdir() if (m := _FRAME_RE.match(p.name)))
    if not numbered:
        raise SequenceFormatError(f"{d} holds no frame files (expected 000000.npz, 000001.npz, ...)")
    for expected, (num, _) in enumerate(numbered):
        if num != expected:
            raise SequenceFormatError(f"missing frame {frame_path(d, expected)} (frames must be numbered 0..n-1)")
    return [p for _, p in numbered]


def _validate(arrays: dict[str, np.ndarray], where: str, raw_classes: bool = False) -> dict[str, np.ndarray]:
    """Check shapes/values and convert to the in-memory dtypes; errors name ``where``.
    ``raw_classes``: ``classes`` are a dataset's category ids (any integers, kept as int64)
    instead of the meta-class ids 0..4."""
    out: dict[str, np.ndarray] = {}
    n = None
    for key in ("points", "flow", "classes", "instance", "ground", "dynamic"):
        if key in arrays:
            n_key = np.shape(arrays[key])[0] if np.ndim(arrays[key]) >= 1 else None
            if n is None:
                n = n_key
            elif n_key != n:
                raise SequenceFormatError(f"{where}: '{key}' has {n_key} entries but the frame has {n} points")
    for key, a in arrays.items():
        if key not in FRAME_KEYS:
            continue  # tolerate extra keys (e.g. intensity) but do not load them
        a = np.asarray(a)
        if key in ("points", "flow"):
            if a.ndim != 2 or a.shape[1] != 3:
                raise SequenceFormatError(f"{where}: '{key}' must have shape (N, 3), got {a.shape}")
            if not np.issubdtype(a.dtype, np.number) or not np.all(np.isfinite(a)):
                raise SequenceFormatError(f"{where}: '{key}' must be finite numbers")
        elif key == "pose":
            if a.shape != (4, 4):
                raise SequenceFormatError(f"{where}: 'pose' must have shape (4, 4), got {a.shape}")
        elif key == "classes" and raw_classes:
            if a.ndim != 1 or not np.issubdtype(a.dtype, np.integer):
                raise SequenceFormatError(f"{where}: 'classes' must be ({n},) integers, got {a.shape} {a.dtype}")
            out[key] = a.astype(np.int64)
            continue
        else:
            if a.ndim != 1:
                raise SequenceFormatError(f"{where}: '{key}' must have shape (N,), got {a.shape}")
            if key == "classes" and a.size and (a.min() < 0 or a.max() >= len(CLASS_NAMES)):
                raise SequenceFormatError(f"{where}: 'classes' values must be in 0..{len(CLASS_NAMES) - 1}")
        out[key] = a.astype(_MEM_DTYPES[key], copy=False)
    return out


def write_frame(path: str | os.PathLike, frame: Frame | None = None, **arrays: np.ndarray) -> Path:
    """Write a frame (a ``Frame`` and/or keyword arrays) atomically as compressed npz."""
    path = Path(path)
    data = frame.arrays() if frame is not None else {}
    data.update({k: v for k, v in arrays.items() if v is not None})
    unknown = set(data) - set(FRAME_KEYS)
    if unknown:
        raise ValueError(f"unknown frame keys {sorted(unknown)}; allowed: {FRAME_KEYS}")
    if "points" not in data and "flow" not in data:
        raise ValueError("a frame needs 'points' (ground truth) or 'flow' (prediction)")
    data = _validate(data, str(path))
    disk = {k: np.ascontiguousarray(v, dtype=_DISK_DTYPES[k]) for k, v in data.items()}
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as fh:  # a file object stops numpy from appending '.npz'
            np.savez_compressed(fh, **disk)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def read_frame(path: str | os.PathLike, require: Iterable[str] = ("points",), raw_classes: bool = False
               ) -> Frame | dict:
    """Read one frame file; ``require`` lists keys that must be present. ``raw_classes``: its
    ``classes`` are a dataset's category ids (int64, any integers; ``floxels eval --categories``)
    instead of the meta-class ids 0..4.

    Returns a ``Frame`` when ``points`` is present, otherwise a dict of arrays
    (prediction files may hold only ``flow``).
    """
    path = Path(path)
    if not path.is_file():
        raise SequenceFormatError(f"missing frame file {path}")
    try:
        with open_npz(path) as z:
            arrays = {k: z[k] for k in z.files}
    except Exception as e:  # zip/npy errors come in many types
        raise SequenceFormatError(f"{path}: cannot read as .npz ({e})") from None
    missing = [k for k in require if k not in arrays]
    if missing:
        raise SequenceFormatError(f"{path}: missing key(s) {missing} (present: {sorted(arrays)})")
    arrays = _validate(arrays, str(path), raw_classes)
    if "points" in arrays:
        return Frame(**arrays)
    return arrays


def save_sequence(directory: str | os.PathLike, seq: Sequence) -> Path:
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    for i, fr in enumerate(seq.frames):
        write_frame(frame_path(d, i), fr)
    if seq.meta:
        tmp = d / f".{_META_NAME}.{os.getpid()}.tmp"
        tmp.write_text(json.dumps(seq.meta, indent=2, sort_keys=True, default=str) + "\n")
        os.replace(tmp, d / _META_NAME)
    return d


def load_sequence(directory: str | os.PathLike, require: Iterable[str] = ("points",)) -> Sequence:
    """Load every frame of a sequence directory (see the module docstring)."""
    require = tuple(require)
    paths = list_frames(directory)
    frames = [read_frame(p, require=require) for p in paths]
    for p, fr in zip(paths, frames):
        if not isinstance(fr, Frame):
            raise SequenceFormatError(f"{p}: missing key(s) ['points']")
    meta_file = Path(directory) / _META_NAME
    meta = json.loads(meta_file.read_text()) if meta_file.is_file() else {}
    return Sequence(frames=frames, meta=meta)
