"""Sensor poses (sensor-to-world 4x4 matrices, one per frame) from the common files.

=========================  ===================================================================
file                       format
=========================  ===================================================================
``*.txt``                  one pose per line: 12 values (KITTI odometry: row-major 3x4), 16
                           values (row-major 4x4) or 8 values (TUM: t tx ty tz qx qy qz qw);
                           blank lines and ``#`` comments are ignored
``*.npy``                  (F, 4, 4), (F, 3, 4), (F, 12) or (F, 16)
``*.npz``                  key ``poses`` (else the only array), same shapes as ``.npy``
``*.feather``              Argoverse 2 ``city_SE3_egovehicle.feather``: timestamp_ns, qw, qx,
                           qy, qz, tx_m, ty_m, tz_m (see :func:`read_av2_poses`)
=========================  ===================================================================

KITTI odometry poses are those of the left camera; give the sequence's ``calib.txt`` (its
``Tr:`` line, velodyne-to-camera) to turn them into velodyne poses: ``Tr^-1 P Tr``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from floxels_ext.lidar.io._arrow import column_values
from floxels_ext.lidar.io._optional import require
from floxels_ext.numpy_files import load_npy, open_npz

__all__ = ["PoseFormatError", "read_poses", "read_kitti_calib", "read_av2_poses", "match_timestamps",
           "check_poses", "quat_to_matrix"]


class PoseFormatError(ValueError):
    """A poses file is malformed or does not fit the frames."""


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions (w, x, y, z), normalised here, to (..., 3, 3) rotation matrices."""
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def check_poses(poses, where: str) -> np.ndarray:
    """Validate/convert to (F, 4, 4) float64: finite, rotation part orthonormal (det +1), last row
    (0, 0, 0, 1). Accepts (F,4,4), (F,3,4), (F,12), (F,16) and a single (4,4)."""
    a = np.asarray(poses, dtype=np.float64)
    if a.shape == (4, 4):
        a = a[None]
    if a.ndim == 2 and a.shape[1] in (12, 16):
        a = a.reshape(len(a), -1, 4)
    if a.ndim != 3 or a.shape[1:] not in ((3, 4), (4, 4)):
        raise PoseFormatError(f"{where}: poses must have shape (F, 4, 4), (F, 3, 4), (F, 12) or (F, 16), "
                              f"got {a.shape}")
    if a.shape[1] == 3:
        a = np.concatenate([a, np.broadcast_to([[[0.0, 0, 0, 1]]], (len(a), 1, 4))], axis=1)
    if not np.all(np.isfinite(a)):
        bad = int(np.flatnonzero(~np.isfinite(a).all(axis=(1, 2)))[0])
        raise PoseFormatError(f"{where}: pose {bad} has NaN/inf entries")
    R = a[:, :3, :3]
    err = np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max(axis=(1, 2)) if len(a) else np.zeros(0)
    bad = np.flatnonzero((err > 1e-3) | (np.linalg.det(R) < 0) | (np.abs(a[:, 3] - [0, 0, 0, 1]).max(axis=1) > 1e-9))
    if bad.size:
        raise PoseFormatError(f"{where}: pose {int(bad[0])} is not a rigid transform (rotation part not "
                              f"orthonormal with det +1, or last row not 0 0 0 1)")
    return a


def read_kitti_calib(path) -> np.ndarray:
    """The 4x4 velodyne-to-camera transform ``Tr`` of a KITTI odometry ``calib.txt``."""
    p = Path(path)
    if not p.is_file():  # named as such, not a bare "[Errno 2] No such file or directory"
        raise PoseFormatError(f"{p}: calib file does not exist" if not p.exists() else f"{p}: calib is not a file")
    try:
        text = p.read_text()
    except UnicodeDecodeError:
        raise PoseFormatError(f"{p}: not a text file (KITTI calib.txt expected)") from None
    for line in text.splitlines():
        if line.startswith("Tr:"):
            vals = line.split()[1:]
            if len(vals) != 12:
                raise PoseFormatError(f"{path}: 'Tr:' needs 12 values, got {len(vals)}")
            try:
                a = np.array(vals, np.float64).reshape(1, 12)
            except ValueError:
                raise PoseFormatError(f"{path}: 'Tr:' values are not numbers") from None
            return check_poses(a, str(path))[0]
    raise PoseFormatError(f"{path}: no 'Tr:' line (KITTI calib.txt expected)")


def _read_txt(path: Path) -> np.ndarray:
    rows = []
    for k, line in enumerate(path.read_text().splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        try:
            vals = [float(v) for v in line.replace(",", " ").split()]
        except ValueError:
            raise PoseFormatError(f"{path}:{k}: not a list of numbers: {line[:60]!r}") from None
        if len(vals) not in (8, 12, 16):
            raise PoseFormatError(f"{path}:{k}: {len(vals)} values; expected 12 (KITTI 3x4), 16 (4x4) or "
                                  f"8 (TUM: t tx ty tz qx qy qz qw)")
        if rows and len(vals) != len(rows[0]):
            raise PoseFormatError(f"{path}:{k}: {len(vals)} values but earlier lines have {len(rows[0])}")
        rows.append(vals)
    if not rows:
        raise PoseFormatError(f"{path}: no poses")
    a = np.array(rows)
    if a.shape[1] == 8:  # TUM: translation, then quaternion x y z w
        T = np.tile(np.eye(4), (len(a), 1, 1))
        T[:, :3, :3] = quat_to_matrix(a[:, [7, 4, 5, 6]])
        T[:, :3, 3] = a[:, 1:4]
        return T
    return a


def read_poses(path, *, calib=None) -> np.ndarray:
    """(F, 4, 4) float64 sensor-to-world poses from a poses file (see the module docstring).
    ``calib``: a KITTI ``calib.txt`` to convert camera poses to velodyne poses."""
    p = Path(path)
    if not p.is_file():
        raise PoseFormatError(f"{p}: poses file does not exist" if not p.exists() else f"{p}: not a file")
    suffix = p.suffix.lower()
    try:
        if suffix == ".npy":
            a = load_npy(p)
        elif suffix == ".npz":
            with open_npz(p) as z:
                keys = z.files
                if "poses" in keys:
                    a = z["poses"]
                elif len(keys) == 1:
                    a = z[keys[0]]
                else:
                    raise PoseFormatError(f"{p}: no 'poses' array among keys {sorted(keys)}")
        elif suffix == ".feather":
            return read_av2_poses(p)[1]
        else:
            a = _read_txt(p)
    except PoseFormatError:
        raise
    except (OSError, ValueError, UnicodeDecodeError) as e:
        raise PoseFormatError(f"{p}: cannot read poses ({e})") from None
    poses = check_poses(a, str(p))
    if calib is not None:
        tr = read_kitti_calib(calib)
        poses = np.linalg.inv(tr) @ poses @ tr
    return poses


def read_av2_poses(path) -> tuple[np.ndarray, np.ndarray]:
    """(timestamps_ns (M,) int64, poses (M, 4, 4)) of an Argoverse 2 ``city_SE3_egovehicle.feather``."""
    feather = require("pyarrow.feather", "av2", "pyarrow", "reading Argoverse 2 poses")
    try:
        t = feather.read_table(str(path))
    except Exception as e:
        raise PoseFormatError(f"{path}: cannot read as Feather/Arrow ({e})") from None
    need = ["timestamp_ns", "qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m"]
    missing = [c for c in need if c not in t.column_names]
    if missing:
        raise PoseFormatError(f"{path}: missing column(s) {missing} (columns: {t.column_names})")
    col = {c: column_values(t.column(c)) for c in need}  # (_arrow: no pandas import in an engine's first AV2 log)
    T = np.tile(np.eye(4), (len(col["qw"]), 1, 1))
    T[:, :3, :3] = quat_to_matrix(np.stack([col[c] for c in ("qw", "qx", "qy", "qz")], -1))
    T[:, :3, 3] = np.stack([col[c] for c in ("tx_m", "ty_m", "tz_m")], -1)
    return col["timestamp_ns"].astype(np.int64), check_poses(T, str(path))


def match_timestamps(pose_times: np.ndarray, poses: np.ndarray, frame_times, where: str,
                     tolerance_ns: int = 5_000_000) -> np.ndarray:
    """Pose of each frame time: the pose stamped nearest to it, which must lie within
    ``tolerance_ns`` (AV2 stores a pose at every sweep's own timestamp)."""
    pose_times = np.asarray(pose_times, np.int64)
    order = np.argsort(pose_times)
    pt, ps = pose_times[order], poses[order]
    out = []
    for ft in frame_times:
        k = int(np.searchsorted(pt, ft))
        cand = [c for c in (k - 1, k) if 0 <= c < len(pt)]
        best = min(cand, key=lambda c: abs(int(pt[c]) - int(ft))) if cand else None
        if best is None or abs(int(pt[best]) - int(ft)) > tolerance_ns:
            raise PoseFormatError(f"{where}: no pose within {tolerance_ns / 1e6:g} ms of frame timestamp {ft}")
        out.append(ps[best])
    return np.stack(out) if out else np.zeros((0, 4, 4))
