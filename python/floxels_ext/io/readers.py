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
                    the column count comes from the file size, or ``bin_columns``
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
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ._optional import MissingDependencyError, require

_XYZ = ("x", "y", "z")

__all__ = ["LidarScan", "LidarFormatError", "READERS", "SUFFIXES", "read_points", "read_bin", "read_npy",
           "read_npz", "read_pcd", "read_ply", "read_feather", "natural_key", "lzf_decompress"]


class LidarFormatError(ValueError):
    """A frame file cannot be read (corrupt, truncated, unsupported variant, no points)."""


@dataclass
class LidarScan:
    points: np.ndarray                               # (N, 3) float32, file order, NaN rows kept
    fields: dict[str, np.ndarray] = field(default_factory=dict)  # extra per-point columns
    pose: np.ndarray | None = None                   # (4, 4) float64 sensor-to-world, if the file has one
    timestamp_ns: int | None = None

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
    pts = np.ascontiguousarray(xyz, dtype=np.float32)
    return LidarScan(pts, {k: np.ascontiguousarray(v) for k, v in (fields or {}).items()}, **kw)


# ----------------------------------------------------------------------------- .bin
def _bin_plausibly_5_columns(flat: np.ndarray) -> bool:
    """Both 4 and 5 columns fit the size: a 5th (ring) column holds small integers, whereas
    reading a 4-column file with 5 columns puts coordinates there."""
    ring = flat.reshape(-1, 5)[:, 4]
    return bool(np.all(np.isfinite(ring)) and np.all(ring == np.round(ring)) and np.all((ring >= 0) & (ring < 1024)))


def _disorder(a: np.ndarray) -> float:
    """How far consecutive rows of x, y, z jump, relative to each column's spread (median
    |step| / interquartile range, averaged over x, y, z). Lidar files are stored in scan
    order, so read with the right column count this is small (~0.01); read with a wrong
    count, each column mixes x, y, z and intensity and it is large. Shuffled points give
    ~0.5 for every count (no evidence either way). Median over the three columns: one
    noisy column (e.g. z of a flat ground) does not hide the others' order."""
    xyz = a[:, :3].astype(np.float64)
    xyz = xyz[np.isfinite(xyz).all(1)][:200_000]
    if xyz.shape[0] < 16:
        return float("nan")
    q75, q25 = np.percentile(xyz, [75, 25], axis=0)
    step = np.median(np.abs(np.diff(xyz, axis=0)), axis=0)
    return float(np.median(step / np.maximum(q75 - q25, 1e-6)))


def _check_bin_plausible(path, a: np.ndarray, cols: int, flat: np.ndarray, size: int, explicit: bool) -> None:
    """Refuse a .bin whose values cannot be lidar coordinates (garbage, wrong dtype) or that
    another column count reads clearly better than ``cols`` (a wrong ``--bin-columns``)."""
    # NaN rows are legitimate (kept, flagged invalid); huge finite values are what random
    # bytes or another dtype read as float32 look like. Judged on <= 8192 evenly spaced rows
    # (the whole file only when none of them is finite): the full pass cost more than reading.
    step = max(1, len(a) // 8192)
    xyz = a[::step, :3]
    with np.errstate(invalid="ignore", over="ignore"):
        bad = (np.isfinite(xyz) & (np.abs(xyz) > 1e5)).any(1)
    frac = float(bad.mean())
    if not np.isfinite(xyz).all(1).any():
        xyz = a[:, :3]
    if frac > 0.1 or not np.isfinite(xyz).all(1).any():
        what = f"{100 * frac:.0f}% of the {len(a)} rows" if frac > 0.1 else f"none of the {len(a)} rows"
        raise _fail(path, f"{what} read with {cols} float32 columns have "
                          + ("coordinates beyond 100 km" if frac > 0.1 else "finite coordinates")
                          + ": not a float32 x y z ... .bin lidar file, "
                          f"or the wrong column count" + ("" if explicit else " (set it with --bin-columns)"))
    if not explicit:
        return
    score = {c: _disorder(flat.reshape(-1, c)) for c in range(3, 9) if size % (4 * c) == 0}
    score = {c: v for c, v in score.items() if np.isfinite(v)}
    if cols not in score or len(score) < 2:
        return
    low = min(score.values())
    # the smallest count that reads the rows in order (a multiple of the true count reads
    # x, y, z of every other row in order too, losing the rows between)
    best = min(c for c, v in score.items() if v <= 2 * low)
    if low < 0.1 and best != cols:
        raise _fail(path, f"reading it with {cols} columns (--bin-columns) scrambles the coordinates: "
                          f"the rows look like {best} float32 columns (KITTI has 4, nuScenes 5); "
                          f"use --bin-columns {best} or leave it out")


def read_bin(path, bin_columns: int | None = None) -> LidarScan:
    """KITTI (x, y, z, intensity) or nuScenes (x, y, z, intensity, ring) float32 ``.bin``.

    ``bin_columns`` forces the column count; it is refused when the file's size is not a
    whole number of such rows or when another count reads the file clearly better (rows in
    scan order). Files whose values are mostly NaN/inf or beyond 100 km are refused."""
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
        flat = np.fromfile(path, dtype="<f4")
        cols = fits[0] if len(fits) == 1 else (5 if _bin_plausibly_5_columns(flat) else 4)
    else:
        if size % (4 * bin_columns):
            raise _fail(path, f"size {size} bytes is not a whole number of rows of {bin_columns} float32 columns "
                              f"(--bin-columns {bin_columns}); truncated, or a different column count?")
        flat = np.fromfile(path, dtype="<f4")
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
        a = np.load(path, allow_pickle=False)
    except Exception as e:  # numpy raises many kinds for a bad header / truncated data
        raise _fail(path, f"cannot read as .npy ({e})") from None
    return _finish(path, *_array_points(path, a, "array"))


def read_npz(path) -> LidarScan:
    """Key ``points`` (else the first (N, >=3) numeric array); ``pose`` (4, 4) when present."""
    try:
        with np.load(path, allow_pickle=False) as z:
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


# ----------------------------------------------------------------------------- .pcd
_PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4", ("I", 8): "i8",
              ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8", ("F", 2): "f2"}


def lzf_decompress(data: bytes, out_len: int) -> bytes:
    """LZF (liblzf) decompression, as used by PCD ``binary_compressed``. A control byte < 32
    starts a run of ctrl+1 literal bytes; otherwise its top 3 bits are a length (7: read one
    more byte) and the rest plus the next byte an offset back into the output."""
    out = bytearray()
    i, n = 0, len(data)
    while i < n:
        ctrl = data[i]
        i += 1
        if ctrl < 32:
            run = ctrl + 1
            if i + run > n:
                raise ValueError("LZF literal run past the end of the input")
            out += data[i:i + run]
            i += run
            continue
        length = ctrl >> 5
        if length == 7:
            if i >= n:
                raise ValueError("LZF input ends inside a back-reference")
            length += data[i]
            i += 1
        if i >= n:
            raise ValueError("LZF input ends inside a back-reference")
        ref = len(out) - ((ctrl & 0x1F) << 8) - data[i] - 1
        i += 1
        length += 2
        if ref < 0:
            raise ValueError("LZF back-reference before the start of the output")
        if ref + length <= len(out):
            out += out[ref:ref + length]
        else:  # overlapping copy: repeats the last bytes
            for k in range(length):
                out.append(out[ref + k])
    if len(out) != out_len:
        raise ValueError(f"LZF data decompressed to {len(out)} bytes, header says {out_len}")
    return bytes(out)


def read_pcd(path) -> LidarScan:
    raw = Path(path).read_bytes()
    header: dict[str, list[str]] = {}
    pos = 0
    while True:
        end = raw.find(b"\n", pos)
        if end < 0:
            raise _fail(path, "PCD header has no DATA line (truncated or not a .pcd file)")
        line = raw[pos:end].decode("ascii", "replace").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *vals = line.split()
        header[key.upper()] = vals
        if key.upper() == "DATA":
            break
    try:
        names = header["FIELDS"]
        sizes = [int(s) for s in header["SIZE"]]
        types = [t.upper() for t in header["TYPE"]]
        counts = [int(c) for c in header.get("COUNT", ["1"] * len(names))]
        npts = int(header["POINTS"][0]) if "POINTS" in header else (
            int(header["WIDTH"][0]) * int(header.get("HEIGHT", ["1"])[0]))
        mode = header["DATA"][0].lower()
    except (KeyError, ValueError, IndexError) as e:
        raise _fail(path, f"bad PCD header ({e!r})") from None
    if not (len(names) == len(sizes) == len(types) == len(counts)):
        raise _fail(path, "PCD header: FIELDS, SIZE, TYPE and COUNT have different lengths")
    missing = [c for c in "xyz" if c not in names]
    if missing:
        raise _fail(path, f"PCD has no field(s) {missing} (fields: {names})")
    dts = []
    for nm, s, t, c in zip(names, sizes, types, counts):
        if (t, s) not in _PCD_TYPES:
            raise _fail(path, f"PCD field {nm!r}: unsupported TYPE {t} with SIZE {s}")
        dts.append((nm if nm != "_" else f"_pad{len(dts)}", "<" + _PCD_TYPES[(t, s)], (c,) if c > 1 else ()))
    dtype = np.dtype(dts)
    body = raw[pos:]
    if npts == 0:
        raise _fail(path, "the frame has no points (POINTS 0)")
    if mode == "ascii":
        try:
            vals = np.array(body.decode("ascii").split(), dtype=np.float64)
        except (UnicodeDecodeError, ValueError) as e:
            raise _fail(path, f"bad ASCII PCD data ({e})") from None
        per = sum(counts)
        if vals.size != npts * per:
            raise _fail(path, f"ASCII PCD data has {vals.size} values, expected {npts} points x {per}")
        vals = vals.reshape(npts, per)
        col = {nm: vals[:, sum(counts[:k])] for k, nm in enumerate(names)}
        xyz = np.stack([col[c] for c in "xyz"], 1)
        extra = {nm: col[nm] for nm, c in zip(names, counts) if nm not in _XYZ and nm != "_" and c == 1}
        return _finish(path, xyz, extra)
    if mode == "binary":
        need = npts * dtype.itemsize
        if len(body) < need:
            raise _fail(path, f"binary PCD data is truncated: {len(body)} bytes, expected {need}")
        rec = np.frombuffer(body, dtype=dtype, count=npts)
    elif mode == "binary_compressed":
        if len(body) < 8:
            raise _fail(path, "binary_compressed PCD data is truncated")
        csize, usize = np.frombuffer(body[:8], "<u4")
        if usize != npts * dtype.itemsize or len(body) < 8 + csize:
            raise _fail(path, f"binary_compressed PCD sizes do not match the header "
                              f"(compressed {csize}, uncompressed {usize}, have {len(body) - 8} bytes)")
        try:
            data = lzf_decompress(body[8:8 + int(csize)], int(usize))
        except ValueError as e:
            raise _fail(path, f"corrupt binary_compressed PCD data ({e})") from None
        # column-major: each field's values for all points, one field after another
        rec = np.empty(npts, dtype=dtype)
        off = 0
        for nm in dtype.names:
            sub = dtype.fields[nm][0]
            nbytes = sub.itemsize * npts
            rec[nm] = np.frombuffer(data[off:off + nbytes], dtype=sub.base, count=npts * max(1, int(np.prod(sub.shape)))
                                    ).reshape((npts,) + sub.shape)
            off += nbytes
    else:
        raise _fail(path, f"unsupported PCD DATA type {mode!r} (ascii, binary, binary_compressed)")
    xyz = np.stack([rec[c].reshape(npts, -1)[:, 0].astype(np.float64) for c in "xyz"], 1)
    extra = {nm: rec[nm] for nm in dtype.names if nm not in _XYZ and not nm.startswith("_pad")
             and rec[nm].ndim == 1}
    return _finish(path, xyz, extra)


# ----------------------------------------------------------------------------- .ply
_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def read_ply(path) -> LidarScan:
    raw = Path(path).read_bytes()
    if not raw.startswith(b"ply"):
        raise _fail(path, "not a PLY file (no 'ply' magic)")
    end = raw.find(b"end_header")
    if end < 0:
        raise _fail(path, "PLY header has no end_header (truncated?)")
    nl = raw.find(b"\n", end)
    body = raw[nl + 1:] if nl >= 0 else b""
    fmt = None
    elements: list[list] = []  # [name, count, [(prop name, type or ("list", count type, item type))]]
    for line in raw[:end].decode("ascii", "replace").splitlines()[1:]:
        tok = line.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        try:
            if tok[0] == "format":
                fmt = tok[1]
            elif tok[0] == "element":
                elements.append([tok[1], int(tok[2]), []])
            elif tok[0] == "property":
                if tok[1] == "list":
                    elements[-1][2].append((tok[4], ("list", _PLY_TYPES[tok[2]], _PLY_TYPES[tok[3]])))
                else:
                    elements[-1][2].append((tok[2], _PLY_TYPES[tok[1]]))
        except (IndexError, KeyError, ValueError) as e:
            raise _fail(path, f"bad PLY header line {line!r} ({e!r})") from None
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise _fail(path, f"unsupported PLY format {fmt!r}")
    names = [e[0] for e in elements]
    if "vertex" not in names:
        raise _fail(path, f"PLY has no 'vertex' element (elements: {names})")
    vprops = elements[names.index("vertex")][2]
    missing = [c for c in "xyz" if c not in [p[0] for p in vprops]]
    if missing:
        raise _fail(path, f"PLY vertex has no propert(y/ies) {missing}")
    nv = elements[names.index("vertex")][1]
    if nv == 0:
        raise _fail(path, "the frame has no points (0 vertices)")
    if fmt == "ascii":
        lines = body.decode("ascii", "replace").splitlines()
        skip = sum(e[1] for e in elements[:names.index("vertex")])  # one line per item of earlier elements
        rows = lines[skip:skip + nv]
        if len(rows) < nv:
            raise _fail(path, f"ASCII PLY is truncated: {len(rows)} of {nv} vertex lines")
        if any(isinstance(t, tuple) for _, t in vprops):
            raise _fail(path, "PLY vertex elements with list properties are not supported")
        try:
            vals = np.array(" ".join(rows).split(), dtype=np.float64)
        except ValueError as e:
            raise _fail(path, f"bad ASCII PLY vertex data ({e})") from None
        if vals.size != nv * len(vprops):
            raise _fail(path, f"ASCII PLY vertex data has {vals.size} values, expected {nv} x {len(vprops)}")
        vals = vals.reshape(nv, len(vprops))
        col = {p[0]: vals[:, k] for k, p in enumerate(vprops)}
    else:
        bo = "<" if fmt == "binary_little_endian" else ">"
        off = 0
        for name, count, props in elements[:names.index("vertex")]:
            off = _skip_binary_element(path, body, off, count, props, bo)
        if any(isinstance(t, tuple) for _, t in vprops):
            raise _fail(path, "PLY vertex elements with list properties are not supported")
        dtype = np.dtype([(p[0], bo + p[1]) for p in vprops])
        if len(body) - off < nv * dtype.itemsize:
            raise _fail(path, f"binary PLY is truncated: {len(body) - off} bytes for {nv} vertices of "
                              f"{dtype.itemsize} bytes")
        rec = np.frombuffer(body, dtype=dtype, count=nv, offset=off)
        col = {n: rec[n] for n in dtype.names}
    xyz = np.stack([np.asarray(col[c], np.float64) for c in "xyz"], 1)
    return _finish(path, xyz, {k: v for k, v in col.items() if k not in _XYZ})


def _skip_binary_element(path, body: bytes, off: int, count: int, props, bo: str) -> int:
    """Byte offset after ``count`` items of a binary PLY element (list properties walked item by item)."""
    if not any(isinstance(t, tuple) for _, t in props):
        return off + count * np.dtype([(n, bo + t) for n, t in props]).itemsize
    for _ in range(count):
        for _, t in props:
            if isinstance(t, tuple):
                ct = np.dtype(bo + t[1])
                if off + ct.itemsize > len(body):
                    raise _fail(path, "binary PLY is truncated inside an element before 'vertex'")
                k = int(np.frombuffer(body, ct, 1, off)[0])
                off += ct.itemsize + k * np.dtype(t[2]).itemsize
            else:
                off += np.dtype(t).itemsize
    return off


# ----------------------------------------------------------------------------- .feather (AV2)
def read_feather(path) -> LidarScan:
    """An Argoverse 2 sensor sweep: columns x, y, z in the ego-vehicle frame (plus intensity,
    laser_number, offset_ns). The sweep's timestamp (ns) is its file name, when numeric."""
    feather = require("pyarrow.feather", "av2", "pyarrow", "reading Argoverse 2 .feather files")
    try:
        table = feather.read_table(str(path))
    except Exception as e:
        raise _fail(path, f"cannot read as Feather/Arrow ({e})") from None
    cols = table.column_names
    missing = [c for c in "xyz" if c not in cols]
    if missing:
        raise _fail(path, f"no column(s) {missing} (columns: {cols})")
    xyz = np.stack([table.column(c).to_numpy(zero_copy_only=False).astype(np.float64) for c in "xyz"], 1)
    extra = {c: table.column(c).to_numpy(zero_copy_only=False) for c in cols if c not in _XYZ}
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
        raise LidarFormatError(f"{p}: no such file" if not p.exists() else f"{p}: not a regular file")
    try:
        return read_bin(p, bin_columns) if suffix == ".bin" else READERS[suffix](p)
    except (LidarFormatError, MissingDependencyError):
        raise
    except (OSError, ValueError, TypeError, IndexError, KeyError, UnicodeDecodeError) as e:
        raise LidarFormatError(f"{p}: cannot read ({type(e).__name__}: {e})") from None
