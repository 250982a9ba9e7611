"""Readers of the PCL ``.pcd`` (ascii, binary, binary_compressed with LZF) and ``.ply``
(ascii and binary, either byte order) point-cloud formats."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from floxels_ext.lidar.io.scan import LidarScan, _fail, _finish

__all__ = ["read_pcd", "read_ply", "lzf_decompress"]

_XYZ = ("x", "y", "z")


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
