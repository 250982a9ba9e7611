"""Readers for single lidar frames: one function per format, ``read_points`` dispatches by extension.

Every reader returns a :class:`LidarScan` whose ``points`` keep ONE ROW PER STORED POINT, in
file order: rows with NaN/inf coordinates are kept (``valid`` is False for them) so that
per-point outputs (flow, masks) line up with the file. Extra per-point columns (intensity,
ring, ...) go to ``fields``. Any problem raises :class:`LidarFormatError` (a ``ValueError``)
whose message starts with the file's path.

==================  ===========================================================================
extension           format
==================  ===========================================================================
``.bin``            raw float32 rows x, y, z, intensity[, ring] (KITTI: 4 columns, nuScenes: 5);
                    the column count comes from the file size (checked: rows in scan
                    order, a 4th column >= 0), or ``bin_columns``
``.npy``            (N, >=3) numeric array, or a structured array with fields x, y, z
``.npz``            key ``points`` (else the first (N, >=3) array); optional ``pose`` (4, 4)
``.pcd``            PCL point cloud, DATA ascii / binary / binary_compressed (LZF), fields
                    x y z of any type, count and order
``.ply``            ascii / binary_little_endian / binary_big_endian, element ``vertex`` with
                    properties x y z of any type; other elements are skipped
``.feather``        Argoverse 2 sweep (columns x, y, z, ...); needs pyarrow (extra ``av2``)
==================  ===========================================================================
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from floxels_ext.lidar.io._arrow import chunk_values, column_values, one_chunk, xyz_rows
from floxels_ext.lidar.io._optional import MissingDependencyError, require
from floxels_ext.lidar.io.pcd_ply import lzf_decompress, read_pcd, read_ply  # noqa: F401  (lzf_decompress: re-exported)
from floxels_ext.lidar.io.scan import LidarFormatError, LidarScan, _fail, _finish, natural_key
from floxels_ext.numpy_files import load_npy, open_npz

_XYZ = ("x", "y", "z")

__all__ = ["LidarScan", "LidarFormatError", "READERS", "SUFFIXES", "read_points", "read_bin", "read_npy",
           "read_npz", "read_pcd", "read_ply", "read_feather", "natural_key", "lzf_decompress"]


# ----------------------------------------------------------------------------- .bin
def _bin_plausibly_5_columns(flat: np.ndarray) -> bool:
    """Both 4 and 5 columns fit the size: a 5th (ring) column holds small integers, whereas
    reading a 4-column file with 5 columns puts coordinates there."""
    ring = flat.reshape(-1, 5)[:, 4]
    # the first rows first: a 4-column file read as 5 fails there (coordinates in that column),
    # and the verdict is the whole column's either way (~0.2 ms a frame saved on such files)
    return _small_integers(ring[:GUESS_CHECK_ROWS]) and _small_integers(ring)


def _small_integers(ring: np.ndarray) -> bool:
    return bool(np.all(np.isfinite(ring)) and np.all(ring == np.round(ring)) and np.all((ring >= 0) & (ring < 1024)))


def _finite_rows(xyz: np.ndarray) -> np.ndarray:
    """(n,) bool: the rows of (n, 3) ``xyz`` whose three values are finite (column by column:
    ``np.isfinite(xyz).all(1)`` on 3 columns is ~10x slower)."""
    fin = np.isfinite(xyz)
    return fin[:, 0] & fin[:, 1] & fin[:, 2]


def _disorder(a: np.ndarray, rows: int = 200_000) -> float:
    """How far consecutive rows of x, y, z jump, relative to each column's spread (median
    |step| / interquartile range, averaged over x, y, z), on the first ``rows`` finite rows.
    Lidar files are stored in scan order, so read with the right column count this is small
    (~0.01); read with a wrong count, each column mixes x, y, z and intensity and it is large.
    Shuffled points give ~0.5 for every count (no evidence either way). Median over the three
    columns: one noisy column (e.g. z of a flat ground) does not hide the others' order."""
    # the compiled op (csrc/cpu/scan_order_cpu.cpp): numpy's formula to the bit
    # (tests/lidar/test_bin_disorder_reference.py), without the GIL, ~3x faster than numpy's
    # selections (run for every column count the size allows, on every frame of a run)
    from floxels_ext.lidar.preprocess.transform import host_rows
    from floxels_ext.ops.lidar import scan_disorder

    return scan_disorder(host_rows(a[:rows, :3]))


def _ordered_columns(flat: np.ndarray, size: int, rows: int) -> int | None:
    """The column count (3..8, one the file's size allows) whose rows read in scan order, when
    one clearly does (else None): the smallest count within twice the lowest disorder (a
    multiple of the true count reads x, y, z of every other row in order too)."""
    score = {c: _disorder(flat[:rows * c].reshape(-1, c), rows) for c in range(3, 9) if size % (4 * c) == 0}
    score = {c: v for c, v in score.items() if np.isfinite(v)}
    if len(score) < 2:
        return None
    low = min(score.values())
    return min(c for c, v in score.items() if v <= 2 * low) if low < 0.1 else None


def _any_finite_row(xyz: np.ndarray) -> bool:
    return bool(_finite_rows(xyz).any())


# the size guess is checked on the first rows only (scan order shows there; cheap for readers)
GUESS_CHECK_ROWS = 8192


def _check_bin_plausible(path, a: np.ndarray, cols: int, flat: np.ndarray, size: int, explicit: bool) -> None:
    """Refuse a .bin whose values cannot be lidar coordinates (garbage, wrong dtype), that
    another column count reads clearly better than ``cols`` (a wrong ``--bin-columns``, or a
    wrong guess from the size: an x y z-only file whose size also divides by 4 or 5 columns),
    or, for a guessed count, whose 4th column cannot be an intensity (negative values)."""
    # NaN rows are legitimate (kept, flagged invalid); huge finite values are what random
    # bytes or another dtype read as float32 look like. Judged on <= 8192 evenly spaced rows
    # (the whole file only when none of them is finite): the full pass cost more than reading.
    step = max(1, len(a) // 8192)
    xyz = a[::step, :3]
    with np.errstate(invalid="ignore", over="ignore"):
        big = np.isfinite(xyz) & (np.abs(xyz) > 1e5)
    frac = float((big[:, 0] | big[:, 1] | big[:, 2]).mean())  # any over 3 columns, column by column (faster)
    if not _any_finite_row(xyz):
        xyz = a[:, :3]
    if frac > 0.1 or not _any_finite_row(xyz):
        what = f"{100 * frac:.0f}% of the {len(a)} rows" if frac > 0.1 else f"none of the {len(a)} rows"
        raise _fail(path, f"{what} read with {cols} float32 columns have "
                          + ("coordinates beyond 100 km" if frac > 0.1 else "finite coordinates")
                          + ": not a float32 x y z ... .bin lidar file, "
                          f"or the wrong column count" + ("" if explicit else " (set it with --bin-columns)"))
    best = _ordered_columns(flat, size, 200_000 if explicit else GUESS_CHECK_ROWS)
    if explicit:
        if best is not None and best != cols:
            raise _fail(path, f"reading it with {cols} columns (--bin-columns) scrambles the coordinates: "
                              f"the rows look like {best} float32 columns (KITTI has 4, nuScenes 5); "
                              f"use --bin-columns {best} or leave it out")
        return
    guess = f"its size reads as {cols} float32 columns (x y z intensity{' ring' if cols == 5 else ''})"
    if best is not None and best != cols:
        raise _fail(path, f"{guess}, but its rows look like {best} columns ({'x y z only' if best == 3 else 'in scan order'}); "
                          f"pass --bin-columns {best}")
    inten = a[::step, 3]
    inten = inten[np.isfinite(inten)]
    neg = float((inten < 0).mean()) if len(inten) else 0.0
    if neg > 0.01:  # an intensity is >= 0; a coordinate (x y z-only rows read as 4) is not
        if best is not None:
            hint = f"pass --bin-columns {best}"
        elif size % 12 == 0:
            hint = "pass --bin-columns 3 if the rows are x y z only, or the file's column count"
        else:  # no 3-column reading exists: a KITTI file cut at a size that 5 columns happen to divide
            hint = (f"its size ({size} bytes) is a whole number of rows of no other count among 3 and 4 columns: "
                    f"truncated or damaged? (a KITTI file has 4 columns, 16 bytes a row)")
        why = f" (x y z-only rows read as {cols} columns?)" if best is not None or size % 12 == 0 else ""
        raise _fail(path, f"{guess}, but its 4th column is negative in {100 * neg:.0f}% of the rows: not an "
                          f"intensity{why}; {hint}")


def _read_float32(path, size: int) -> np.ndarray:
    """The file's ``size`` bytes (a multiple of 4) as little-endian float32, read without the
    GIL: ``np.fromfile`` holds it through the read (~0.24 ms a 3.4 MB frame on the 2-core
    CPU, bench/RESULTS.md, reader section), ``readinto`` gives it up around the system call."""
    flat = np.empty(size // 4, "<f4")
    buf = flat.view(np.uint8)
    got = 0
    with open(path, "rb", buffering=0) as f:
        while got < size:
            n = f.readinto(buf[got:])
            if not n:
                break
            got += n
    if got != size:
        raise _fail(path, f"{size} bytes listed but only {got} could be read: the file shrank while being read")
    return flat


def read_bin(path, bin_columns: int | None = None) -> LidarScan:
    """KITTI (x, y, z, intensity) or nuScenes (x, y, z, intensity, ring) float32 ``.bin``.

    ``bin_columns`` forces the column count; it is refused when the file's size is not a
    whole number of such rows or when another count reads the file clearly better (rows in
    scan order). Without it the count comes from the size (4, or 5 with a small-integer ring
    column), refused when another count reads the rows clearly better or when the 4th column
    is negative (not an intensity): an x y z-only file needs ``bin_columns=3``. Files whose
    values are mostly NaN/inf or beyond 100 km are refused."""
    size = os.path.getsize(path)
    if bin_columns is not None and (isinstance(bin_columns, bool) or not isinstance(bin_columns, (int, np.integer))
                                    or bin_columns < 3):
        raise ValueError(f"bin_columns must be an integer >= 3, got {bin_columns!r}")
    if size == 0:
        raise _fail(path, "the frame has no points (empty file)")
    if bin_columns is None:
        fits = [c for c in (4, 5) if size % (4 * c) == 0]
        if not fits:
            raise _fail(path, f"size {size} bytes is not a whole number of float32 rows of 4 (KITTI) or "
                              f"5 (nuScenes) columns; truncated? (use --bin-columns to set the column count)")
        flat = _read_float32(path, size)
        cols = fits[0] if len(fits) == 1 else (5 if _bin_plausibly_5_columns(flat) else 4)
    else:
        if size % (4 * bin_columns):
            raise _fail(path, f"size {size} bytes is not a whole number of rows of {bin_columns} float32 columns "
                              f"(--bin-columns {bin_columns}); truncated, or a different column count?")
        flat = _read_float32(path, size)
        cols = int(bin_columns)
    a = flat.reshape(-1, cols)
    _check_bin_plausible(path, a, cols, flat, size, explicit=bin_columns is not None)
    names = ["intensity", "ring"] + [f"c{i}" for i in range(5, cols)]
    return _finish(path, a[:, :3], {names[i - 3]: a[:, i] for i in range(3, cols)})


# ----------------------------------------------------------------------------- .npy / .npz
def _array_points(path, a: np.ndarray, what: str) -> tuple[np.ndarray, dict]:
    if a.dtype.names:  # structured array: fields x, y, z (+ others)
        missing = [c for c in "xyz" if c not in a.dtype.names]
        if missing:
            raise _fail(path, f"{what}: structured array lacks field(s) {missing} (has {list(a.dtype.names)})")
        a = a.reshape(-1)
        return (np.stack([a[c].astype(np.float64) for c in "xyz"], 1),
                {n: a[n] for n in a.dtype.names if n not in _XYZ and a[n].ndim == 1})
    if a.ndim != 2 or a.shape[1] < 3:
        raise _fail(path, f"{what}: expected an (N, >=3) array, got shape {a.shape}"
                    + (" (transposed? save arr.T)" if a.ndim == 2 and a.shape[0] in (3, 4, 5) else ""))
    if 3 <= a.shape[0] <= 8 and a.shape[1] > a.shape[0]:
        # (3, N) is far more often a transposed cloud than N=3 points with many columns
        raise _fail(path, f"{what}: shape {a.shape} looks transposed (coordinates along rows); points must be "
                          f"rows: save it as shape ({a.shape[1]}, {a.shape[0]}) (arr.T)")
    if a.shape[1] > 64:
        raise _fail(path, f"{what}: shape {a.shape}: {a.shape[1]} columns per point is not a lidar frame "
                          f"(expected (N, >=3) with x, y, z first)")
    if not np.issubdtype(a.dtype, np.number) or np.issubdtype(a.dtype, np.complexfloating):
        raise _fail(path, f"{what}: coordinates must be real numbers, got dtype {a.dtype}")
    return a[:, :3], {("intensity" if i == 3 else f"c{i}"): a[:, i] for i in range(3, a.shape[1])}


def read_npy(path) -> LidarScan:
    try:
        a = load_npy(path)
    except Exception as e:  # numpy raises many kinds for a bad header / truncated data
        raise _fail(path, f"cannot read as .npy ({e})") from None
    return _finish(path, *_array_points(path, a, "array"))


def read_npz(path) -> LidarScan:
    """Key ``points`` (else the first (N, >=3) numeric array); ``pose`` (4, 4) when present."""
    try:
        with open_npz(path) as z:
            arrays = {k: z[k] for k in z.files}
    except Exception as e:
        raise _fail(path, f"cannot read as .npz ({e})") from None
    key = "points" if "points" in arrays else next(
        (k for k, v in arrays.items() if v.ndim == 2 and v.shape[1] >= 3 and np.issubdtype(v.dtype, np.number)), None)
    if key is None:
        raise _fail(path, f"no 'points' array and no (N, >=3) array among keys {sorted(arrays)}")
    xyz, fields = _array_points(path, arrays[key], f"'{key}'")
    n = xyz.shape[0]
    fields.update({k: v for k, v in arrays.items() if k not in (key, "pose") and v.ndim >= 1 and v.shape[0] == n
                   and v.ndim <= 2})
    pose = arrays.get("pose")
    if pose is not None:
        pose = np.asarray(pose, np.float64)
        if pose.shape != (4, 4):
            raise _fail(path, f"'pose' must have shape (4, 4), got {pose.shape}")
    return _finish(path, xyz, fields, pose=pose)


# ----------------------------------------------------------------------------- .feather (AV2)
def read_feather(path) -> LidarScan:
    """An Argoverse 2 sensor sweep: columns x, y, z in the ego-vehicle frame (plus intensity,
    laser_number, offset_ns). The sweep's timestamp (ns) is its file name, when numeric."""
    feather = require("pyarrow.feather", "av2", "pyarrow", "reading Argoverse 2 .feather files")
    pa_types = require("pyarrow.types", "av2", "pyarrow", "reading Argoverse 2 .feather files")
    try:
        table = feather.read_table(str(path))
    except Exception as e:
        raise _fail(path, f"cannot read as Feather/Arrow ({e})") from None
    cols = table.column_names
    missing = [c for c in "xyz" if c not in cols]
    if missing:
        raise _fail(path, f"no column(s) {missing} (columns: {cols})")
    for c in "xyz":
        if not (pa_types.is_floating(table.column(c).type) or pa_types.is_integer(table.column(c).type)):
            raise _fail(path, f"column {c!r} holds {table.column(c).type}, not numbers")
    # float32 rows (AV2 stores float16: exact; float64 rounds once, as before) without pyarrow's
    # pandas converter (``_arrow``): in Arrow's calls without the GIL where the columns allow,
    # else chunk by chunk (a file holds record batches of 64k rows) from their buffers
    table = one_chunk(table)
    xyz = xyz_rows(table)
    if xyz is None:
        xyz = np.empty((table.num_rows, 3), np.float32)
        for k, c in enumerate("xyz"):
            row = 0
            for chunk in table.column(c).chunks:
                xyz[row:row + len(chunk), k] = chunk_values(chunk)
                row += len(chunk)
    extra = {c: column_values(table.column(c)) for c in cols if c not in _XYZ}
    stem = Path(path).stem
    return _finish(path, xyz, extra, timestamp_ns=int(stem) if stem.isdigit() else None)


READERS = {".bin": read_bin, ".npy": read_npy, ".npz": read_npz, ".pcd": read_pcd, ".ply": read_ply,
           ".feather": read_feather}
SUFFIXES = tuple(READERS)


def read_points(path, *, bin_columns: int | None = None) -> LidarScan:
    """Read one lidar frame, choosing the reader by file extension (see the module docstring)."""
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in READERS:
        raise LidarFormatError(f"{p}: unknown lidar file extension {p.suffix!r}; supported: {', '.join(SUFFIXES)}")
    if not p.is_file():
        if p.is_symlink() and not p.exists():
            raise LidarFormatError(f"{p}: broken symbolic link (to {os.readlink(p)}, which does not exist)")
        raise LidarFormatError(f"{p}: no such file" if not p.exists() else f"{p}: not a regular file")
    try:
        return read_bin(p, bin_columns) if suffix == ".bin" else READERS[suffix](p)
    except (LidarFormatError, MissingDependencyError):
        raise
    except (OSError, ValueError, TypeError, IndexError, KeyError, UnicodeDecodeError) as e:
        raise LidarFormatError(f"{p}: cannot read ({type(e).__name__}: {e})") from None
