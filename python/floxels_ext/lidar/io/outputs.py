"""The files ``floxels run`` writes, and the one reader for them (:func:`read_flow_output`).

One ``OUT_DIR/<frame name>.npz`` per frame (layout in :data:`OUTPUT`). Writes are atomic (a
hidden temporary name in the same directory, then ``os.replace``), so a file that exists is
complete and an interrupted run resumes by skipping it. Each file records the settings that
produced it (``settings``, JSON) so a resumed run with other settings is detected
(:func:`settings_mismatch`). By default the files are written uncompressed and without the input
points (they are read back from the recorded ``source`` file); ``--self-contained`` stores them.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np

from floxels_ext.numpy_files import open_npz

__all__ = ["OUTPUT", "FORMAT_VERSION", "OutputError", "write_output", "read_flow_output", "cleanup_temps",
           "remove_temps", "read_settings", "read_resume_record", "settings_mismatch", "run_outputs", "points_crc32"]

FORMAT_VERSION = 2

OUTPUT = """\
Output: OUT_DIR/<frame name>.npz per frame (np.savez; --compress: zip-compressed) with
  flow        (N,3) float32  motion to the next frame (metres per frame step), in the frame
                             file's own coordinates and point order; ego-motion compensated
                             (static = 0). Points not optimised (cropped, ground) get 0,
                             rows with NaN/inf input coordinates get NaN.
  mask        (N,)  bool     points that passed cropping and ground removal and were optimised
                             (the points the paper evaluates)
  dynamic     (N,)  bool     optimised points whose |flow| exceeds dynamic_threshold
                             (--dynamic-threshold, metres per frame step; default 0.05, i.e.
                             0.5 m/s at 10 Hz, the Argoverse 2 protocol's dynamic threshold)
  evidence    (N,)  float32  motion evidence (Floxels; absent with --option evidence=off or
                             other methods): metres of distance-transform residual by which
                             the flow of the point's group (its DBSCAN cluster, or for an
                             unclustered point its 0.5 m flow-grid cell) explains the support
                             scans better than zero flow; NaN on points not optimised
  explained   (N,)  bool     the group's flow passes the evidence test (gain > max(margin,
                             ratio * zero-flow residual), FloxelsConfig.evidence_margin/_ratio;
                             accurate: the final verdict, after the refinement confirmed or
                             dropped the groups no scan saw and gave rigid motions to others);
                             by default (evidence=zero) unexplained groups get zero flow and
                             are not 'dynamic'; --raw-flow keeps their optimiser flow (then
                             dynamic & explained are the default's moving points)
  pose        (4,4) float64  the frame's coordinates -> the sequence's world frame
  ego_motion  (4,4) float64  the frame's coordinates -> the next frame's (when the next pose
                             is known, the last selected frame included)
  points      (N,3) float32  the input points (same order): only with --self-contained;
                             otherwise read back from 'source' (floxels_ext.lidar.io.outputs.
                             read_flow_output does either)
  source, bin_columns, points_frame  the frame file and how to read it again
  source_crc32               CRC-32 of the frame's points as read (float32 x y z rows): a
                             source file changed since the run is refused when read back
  timestamp_ns               the frame's time when the input names it (Argoverse 2 sweeps)
  method, num_scans, elapsed_s, options (JSON), dynamic_threshold, format (2),
  settings (JSON: everything that changes the result; a resumed run with other
  settings stops, --force recomputes)
  inputs (JSON: size and modification time of each scan file of the frame's window,
  its poses and times; a resumed run recomputes the frames whose inputs changed)
OUT_DIR/run_summary.json (or --summary FILE): frames, written, skipped, failures with file
names, s/frame and per-stage times of the last run.
"""

_TMP_RE = re.compile(r"^\.(?P<name>.+\.npz)\.\d+\.tmp$")


class OutputError(ValueError):
    """A run output cannot be read (the message names the file)."""


class SourceError(OutputError):
    """The output itself is fine, but the input points it recorded (its ``source`` file) are
    missing, unreadable or changed since the run: callers say so instead of calling the
    output broken."""


def cleanup_temps(out: Path, names=None) -> int:
    """Remove the temporary files an interrupted run left in ``out``; returns how many.

    ``names``: only the temporaries of these output files (``NAME.npz``), so that a run over some
    frames leaves alone those of another run writing other frames of the same directory (Ray
    tasks of one sequence)."""
    n = 0
    for p in out.iterdir():
        m = _TMP_RE.match(p.name)
        if m and (names is None or m.group("name") in names):
            p.unlink(missing_ok=True)
            n += 1
    return n


def write_output(path: Path, *, compress: bool = False, **arrays) -> Path:
    """Atomic .npz write: a temporary name in the same directory, then ``os.replace``."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as fh:
            if compress or not _write_npz_stored(fh, arrays):
                (np.savez_compressed if compress else np.savez)(fh, **arrays)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def _write_npz_stored(fh, arrays: dict) -> bool:
    """What ``np.savez`` writes (a zip of ``NAME.npy`` members, stored), written directly: a
    header per member and the arrays' own memory, CRC-32 by zlib. Why: np.savez runs zipfile's
    Python code and copies each array to bytes, holding the GIL for ~1 ms a frame on the writer
    threads, which the thread driving the GPU waited for; here the big steps (crc32 and the file
    writes of MBs) run without it. Returns False (nothing written) for what this does not cover
    (object arrays, members of 2 GiB or more: zip64); the caller uses np.savez then."""
    import struct
    import time as _time
    import zlib
    from io import BytesIO

    prepared, total = [], 0
    for name, value in arrays.items():
        a = np.asanyarray(value)
        if not a.flags.c_contiguous:  # (not ascontiguousarray: it turns 0-d arrays into 1-d)
            a = a.copy(order="C")
        if a.dtype.hasobject:
            return False
        bio = BytesIO()
        np.lib.format.write_array_header_1_0(bio, np.lib.format.header_data_from_array_1_0(a))
        header = bio.getvalue()
        data = a.reshape(-1).view(np.uint8) if a.size else np.zeros(0, np.uint8)
        total += len(header) + data.nbytes + 100 + 2 * len(name)
        prepared.append(((name + ".npy").encode("utf-8"), header, data))
    if total >= 2**31:
        return False
    t = _time.localtime()
    dos_time = (t.tm_hour << 11) | (t.tm_min << 5) | (t.tm_sec // 2)
    dos_date = ((t.tm_year - 1980) << 9) | (t.tm_mon << 5) | t.tm_mday
    central, offset = [], 0
    for fname, header, data in prepared:
        crc = zlib.crc32(data, zlib.crc32(header))
        size = len(header) + data.nbytes
        fh.write(struct.pack("<IHHHHHIIIHH", 0x04034B50, 20, 0, 0, dos_time, dos_date, crc, size, size,
                             len(fname), 0) + fname + header)
        fh.write(data)
        central.append(struct.pack("<IHHHHHHIIIHHHHHII", 0x02014B50, 20, 20, 0, 0, dos_time, dos_date, crc, size,
                                   size, len(fname), 0, 0, 0, 0, 0o600 << 16, offset) + fname)
        offset += 30 + len(fname) + size
    cd = b"".join(central)
    fh.write(cd + struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, len(central), len(central), len(cd), offset, 0))
    return True


def read_settings(path: Path) -> dict | None:
    """The ``settings`` a run output records (None for files of older versions: their
    method/num_scans/options are returned instead, as far as they are known)."""
    try:
        with open_npz(path) as z:
            if "settings" in z.files:
                return json.loads(str(z["settings"]))
            old = {}
            if "method" in z.files:
                old["method"] = str(z["method"])
            if "options" in z.files:
                old["options"] = json.loads(str(z["options"]))
            return old or None
    except Exception:  # unreadable: not "done"; the caller recomputes it
        return None


def read_resume_record(path: Path) -> dict | None:
    """What a resumed run compares: ``{"settings": ..., "inputs": ...}`` of an output
    (``settings`` as :func:`read_settings` gives it; ``inputs``, the record of
    :mod:`floxels_ext.lidar.pipeline.resume`, None for outputs of earlier versions). None when the file
    cannot be read as an output (truncated, not a zip, no ``flow``, no settings): not done."""
    try:
        with open_npz(path) as z:
            if "flow" not in z.files:
                return None
            inputs = json.loads(str(z["inputs"])) if "inputs" in z.files else None
    except Exception:
        return None
    settings = read_settings(path)
    if settings is None or not isinstance(inputs, (dict, type(None))):
        return None
    return {"settings": settings, "inputs": inputs}


def settings_mismatch(recorded: dict, current: dict) -> list[str]:
    """Human-readable differences between two ``settings`` dicts (keys both know)."""
    cur = json.loads(json.dumps(current, default=str))  # same normal form as the recorded JSON
    return [f"{k}: {recorded[k]!r} (recorded) vs {cur[k]!r} (now)" for k in sorted(set(recorded) & set(cur))
            if recorded[k] != cur[k] and not _same_file(k, recorded[k], cur[k])]


def _same_file(key: str, a, b) -> bool:
    """Paths recorded before they were resolved (relative: against the working directory now)."""
    return key == "pose_source" and isinstance(a, str) and isinstance(b, str) and \
        os.path.realpath(a) == os.path.realpath(b)


def run_outputs(run_dir) -> list[Path]:
    """The frame outputs of a ``floxels run`` OUT_DIR in natural order."""
    from floxels_ext.lidar.io.readers import natural_key

    d = Path(run_dir)
    if not d.is_dir():
        raise FileNotFoundError(f"{d} is not a directory" if d.exists() else f"{d} does not exist")
    files = sorted((p for p in d.glob("*.npz") if not p.name.startswith(".")), key=lambda p: natural_key(p.name))
    if not files:
        raise FileNotFoundError(f"{d} holds no frame outputs (*.npz from floxels run)")
    return files


def points_crc32(points: np.ndarray) -> int:
    """CRC-32 of a frame's points as float32 x y z rows (zlib: ~2 ms a 200k-point frame,
    without the GIL), recorded as ``source_crc32`` so that a changed source file is noticed."""
    import zlib

    pts = np.asarray(points)[:, :3]
    if pts.dtype == np.float32 and not pts.flags.c_contiguous:
        # x y z of wider rows (a .bin's x y z intensity): copied column by column, ~4x faster
        # than numpy's (N, 3) strided copy (~1 ms a 216k-point frame); the same bytes
        rows = np.empty(pts.shape, np.float32)
        for k in range(pts.shape[1]):
            rows[:, k] = pts[:, k]
        return zlib.crc32(rows)
    return zlib.crc32(np.ascontiguousarray(pts, np.float32))


def _source_points(d: dict, path: Path) -> np.ndarray:
    from floxels_ext.lidar.io import read_points

    if "source" not in d:
        raise OutputError(f"{path}: no 'points' and no 'source' recorded; expected an output of 'floxels run'")
    src = Path(str(d["source"]))
    if not src.is_absolute():
        src = path.parent / src
    cols = int(d["bin_columns"]) if "bin_columns" in d and int(d["bin_columns"]) > 0 else None
    try:
        pts = read_points(src, bin_columns=cols).points
    except (ValueError, OSError) as e:
        raise SourceError(f"{path}: its input points are not stored (run without --self-contained) and its "
                          f"source {src} cannot be read: {e}") from None
    pts = np.asarray(pts, np.float32)
    if "source_crc32" in d and len(pts) == len(d["flow"]) and points_crc32(pts) != int(d["source_crc32"]):
        raise SourceError(f"{path}: its source {src} changed since the run wrote this flow (same {len(pts)} points, "
                          f"other coordinates: checksum differs); its flow does not belong to these points. Re-run "
                          f"floxels run (--force) on the current files, or keep the points with --self-contained")
    return pts


def read_flow_output(path, *, points: bool = True) -> dict:
    """One ``floxels run`` output as a dict: ``flow``, ``mask``, ``dynamic``, ``evidence`` and
    ``explained`` (the motion evidence; None in outputs without it), ``pose``,
    ``ego_motion`` (None when unknown), ``points`` (stored, else read from the recorded source
    file; skipped with ``points=False``), ``options``/``settings`` (dicts), ``method``,
    ``num_scans``, ``source``, ``timestamp_ns`` (None when unknown), ``elapsed_s``.
    Errors (:class:`OutputError`) name the file."""
    path = Path(path)
    try:
        with open_npz(path) as z:
            d = {k: z[k] for k in z.files}
    except Exception as e:
        raise OutputError(f"{path}: cannot read ({e})") from None
    if "flow" not in d:
        raise OutputError(f"{path}: no 'flow'; expected an output of 'floxels run'")
    flow = np.asarray(d["flow"])
    if flow.ndim != 2 or flow.shape[1] != 3:
        raise OutputError(f"{path}: 'flow' must be (N, 3), got {flow.shape}")
    n = len(flow)
    out: dict = {"flow": flow}
    if points:
        pts = d["points"] if "points" in d else _source_points(d, path)
        if pts.shape != flow.shape and "points" not in d:  # the source file was replaced since the run
            raise SourceError(f"{path}: its source {d.get('source')} changed since the run wrote this flow (it "
                              f"now holds {len(pts)} points, the flow has {n} rows). Re-run floxels run (--force) "
                              f"on the current files, or keep the points with --self-contained")
        if pts.shape != flow.shape:
            raise OutputError(f"{path}: {len(pts)} points (stored) but 'flow' has {n} rows")
        if "points" not in d and "points_frame" in d and str(d["points_frame"]) == "world":
            pass  # seqio input: the source stores the points in the same (world) frame as written
        out["points"] = np.asarray(pts, np.float32)
    finite = np.isfinite(flow).all(1)
    out["mask"] = np.asarray(d["mask"], bool) if "mask" in d else finite
    if "dynamic" in d:
        out["dynamic"] = np.asarray(d["dynamic"], bool)
    else:
        thr = float(d["dynamic_threshold"]) if "dynamic_threshold" in d else 0.05
        with np.errstate(invalid="ignore"):
            out["dynamic"] = out["mask"] & (np.linalg.norm(np.nan_to_num(flow), axis=1) > thr)
    out["evidence"] = np.asarray(d["evidence"], np.float32) if "evidence" in d else None
    out["explained"] = np.asarray(d["explained"], bool) if "explained" in d else None
    for k in ("mask", "dynamic", "evidence", "explained"):
        if out[k] is not None and out[k].shape != (n,):
            raise OutputError(f"{path}: '{k}' has shape {out[k].shape}, expected ({n},)")
    out["pose"] = np.asarray(d.get("pose", np.eye(4)), np.float64)
    out["ego_motion"] = np.asarray(d["ego_motion"], np.float64) if "ego_motion" in d else None
    for k in ("options", "settings"):
        out[k] = json.loads(str(d[k])) if k in d else {}
    for k in ("method", "source"):
        out[k] = str(d[k]) if k in d else None
    out["num_scans"] = int(d["num_scans"]) if "num_scans" in d else None
    out["timestamp_ns"] = int(d["timestamp_ns"]) if "timestamp_ns" in d else None
    out["elapsed_s"] = float(d["elapsed_s"]) if "elapsed_s" in d else None
    return out


def remove_temps(out_dir: Path, names=None) -> int:
    """Removes the temporary files of interrupted writes in out_dir (only those of the frames
    ``names``, output names without ``.npz``, when given); a missing directory has none."""
    if not Path(out_dir).is_dir():
        return 0
    return cleanup_temps(Path(out_dir), None if names is None else {f"{n}.npz" for n in names})
