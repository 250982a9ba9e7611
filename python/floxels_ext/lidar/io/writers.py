"""Point-cloud writers (binary little-endian PLY), atomic like every output of the project."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

__all__ = ["write_ply"]

_PLY_NAMES = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint",
              "f4": "float", "f8": "double"}


def write_ply(path, points: np.ndarray, ascii: bool = False, **properties: np.ndarray) -> Path:
    """Write (N, 3) points plus per-point ``properties`` (1-D arrays; dtype kept if PLY has it,
    else float32) as a PLY vertex element. ``red``/``green``/``blue`` uint8 give colours."""
    pts = np.asarray(points, np.float32).reshape(-1, 3)
    cols = [("x", pts[:, 0]), ("y", pts[:, 1]), ("z", pts[:, 2])]
    for name, v in properties.items():
        v = np.asarray(v).reshape(-1)
        if v.shape[0] != pts.shape[0]:
            raise ValueError(f"property {name!r} has {v.shape[0]} values for {pts.shape[0]} points")
        if v.dtype == np.bool_:
            v = v.astype(np.uint8)
        if v.dtype.str[1:] not in _PLY_NAMES:
            v = v.astype(np.float32)
        cols.append((name, v))
    dtype = np.dtype([(n, "<" + v.dtype.str[1:]) for n, v in cols])
    rec = np.empty(len(pts), dtype)
    for n, v in cols:
        rec[n] = v
    header = ["ply", f"format {'ascii' if ascii else 'binary_little_endian'} 1.0", "comment floxels_ext",
              f"element vertex {len(pts)}"]
    header += [f"property {_PLY_NAMES[v.dtype.str[1:]]} {n}" for n, v in cols]
    header.append("end_header")
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as fh:
            fh.write(("\n".join(header) + "\n").encode("ascii"))
            if ascii:
                for row in rec:
                    fh.write((" ".join(repr(x.item()) for x in row) + "\n").encode("ascii"))
            else:
                fh.write(rec.tobytes())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path
