"""What every reader returns (:class:`LidarScan`) and raises (:class:`LidarFormatError`), and
the checks they share."""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

__all__ = ["LidarScan", "LidarFormatError", "natural_key"]


class LidarFormatError(ValueError):
    """A frame file cannot be read (corrupt, truncated, unsupported variant, no points)."""


@dataclass
class LidarScan:
    points: np.ndarray                               # (N, 3) float32, file order, NaN rows kept;
                                                     # may be a strided view of the file's rows
    fields: dict[str, np.ndarray] = field(default_factory=dict)  # extra per-point columns
    pose: np.ndarray | None = None                   # (4, 4) float64 sensor-to-world, if the file has one
    timestamp_ns: int | None = None
    # (N, 3) float64, the coordinates as stored, where the file stores float64 (else None):
    # world-frame files at map scale (UTM: 5e6 m, where float32 resolves 0.5 m) keep their
    # precision until ``floxels run`` re-centres them (issue 45)
    exact: np.ndarray | None = None

    @property
    def valid(self) -> np.ndarray:
        """(N,) bool: rows whose three coordinates are finite."""
        return np.isfinite(self.points).all(axis=1)

    def __len__(self) -> int:
        return int(self.points.shape[0])


def natural_key(name: str):
    """Sort key that orders 'frame2' before 'frame10'."""
    return [(0, int(t), "") if t.isdigit() else (1, 0, t) for t in re.split(r"(\d+)", name) if t]


def _fail(path, msg: str) -> LidarFormatError:
    return LidarFormatError(f"{path}: {msg}")


def _finish(path, xyz: np.ndarray, fields: dict | None = None, **kw) -> LidarScan:
    xyz = np.asarray(xyz)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise _fail(path, f"expected (N, 3) coordinates, got shape {xyz.shape}")
    if xyz.shape[0] == 0:
        raise _fail(path, "the frame has no points")
    if not np.issubdtype(xyz.dtype, np.number) or np.issubdtype(xyz.dtype, np.complexfloating):
        raise _fail(path, f"coordinates must be real numbers, got dtype {xyz.dtype}")
    # float32 columns stay views of the rows read (x y z intensity ...): the run's ops read any
    # strides, and the copies cost ~2 ms a 240k-point frame on its reader threads
    pts = xyz if xyz.dtype == np.float32 else xyz.astype(np.float32)
    return LidarScan(pts, dict(fields or {}), exact=xyz if xyz.dtype == np.float64 else None, **kw)
