"""``floxels export RUN --format av2-submission OUT --masks MASKS.zip``: the files of the
Argoverse 2 scene flow challenge, and the zip its leaderboard takes.

The challenge's definitions (argoverse/av2-api, ``src/av2/evaluation/scene_flow/``, v0.3.6):

* which sweeps and points are scored is fixed by the challenge's mask archive (``val-masks.zip``,
  ``test-masks.zip``): one ``<log_id>/<timestamp_ns>.feather`` per scored sweep (every 5th pair
  of a split), one bool column ``mask`` over the sweep's points in file order
  (``make_mask_files.py``: within 50 m in x and y of the ego vehicle and not ground by the map's
  ground height; ``utils.get_eval_point_mask``). A submission holds exactly those files;
* each holds, for the mask's points in order, ``flow_tx_m``, ``flow_ty_m``, ``flow_tz_m``
  (float16) and ``is_dynamic`` (bool), nothing else (``make_submission_archive.validate``);
* the flow of a point of sweep t is where it is at sweep t+1 expressed in sweep t+1's ego frame,
  minus where it is in sweep t's (the label: ``ego1_SE3_ego0 (p + object motion) - p``,
  ``torch/structures/flow.py``), in metres over that pair of sweeps;
* the zip holds those files under the same names (``make_submission_archive.zip``).

A run qualifies when it ran over Argoverse 2 logs (``<log_id>/sensors/lidar/<ts>.feather``: the
log id and timestamps come from there) with the logs' own poses (``city_SE3_egovehicle.feather``:
the ego frames of the challenge; a run with KISS-ICP odometry or --no-ego-motion is refused), and
holds every sweep the masks list (``--partial``: the sweeps it has, said loudly: such a zip is
not a valid submission). Everything is checked before anything is written; the zip is written
last, under a temporary name, so it exists only when every file in it was written. Points of the
mask that the run did not estimate (its crop, its own ground removal) get the ego motion only
(static), and ``is_dynamic`` is the run's ``dynamic`` (its --dynamic-threshold, 0.05 m per frame
period by default, the challenge's threshold).
"""

from __future__ import annotations

import io
import os
import sys
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from floxels_ext.lidar.export.run_frames import ExportError, FrameInfo, displacement_to_next, find_sequences, sequence_infos

__all__ = ["export_av2_submission", "read_mask_index", "av2_sweep_id", "SUBMISSION_COLUMNS"]

SUBMISSION_COLUMNS = ("flow_tx_m", "flow_ty_m", "flow_tz_m", "is_dynamic")
_POSES_FILE = "city_SE3_egovehicle.feather"


@dataclass
class _Sweep:
    info: FrameInfo
    period: float | None
    member: str          # "<log_id>/<timestamp_ns>.feather", in the masks and in the submission


def _feather():
    from floxels_ext.lidar.io._optional import require

    return require("pyarrow.feather", "av2", "pyarrow", "writing Argoverse 2 .feather files")


def av2_sweep_id(info: FrameInfo) -> tuple[str, int] | None:
    """(log id, timestamp ns) of an output whose source is an Argoverse 2 sweep
    (``<log_id>/sensors/lidar/<timestamp_ns>.feather``), else None."""
    if info.source is None or info.timestamp_ns is None:
        return None
    src = Path(info.source)
    if src.suffix != ".feather" or src.parent.name != "lidar" or src.parent.parent.name != "sensors" \
            or src.stem != str(info.timestamp_ns):
        return None
    return src.parents[2].name, info.timestamp_ns


def read_mask_index(masks) -> dict[str, str]:
    """``{"<log_id>/<timestamp_ns>.feather": member}`` of a challenge mask archive."""
    path = Path(masks)
    if not path.is_file():
        raise ExportError(f"--masks {path}: no such file (the challenge's mask archive, e.g. val-masks.zip)")
    try:
        with zipfile.ZipFile(path) as zf:
            names = [n for n in zf.namelist() if n.endswith(".feather")]
    except (zipfile.BadZipFile, OSError) as e:
        raise ExportError(f"--masks {path}: not a zip archive ({e})") from None
    index = {}
    for n in names:
        parts = n.split("/")
        if len(parts) < 2 or not parts[-1][:-len(".feather")].isdigit():
            raise ExportError(f"--masks {path}: member {n!r} is not <log_id>/<timestamp_ns>.feather")
        index["/".join(parts[-2:])] = n
    if not index:
        raise ExportError(f"--masks {path}: holds no <log_id>/<timestamp_ns>.feather masks")
    return index


def _read_mask(zf: zipfile.ZipFile, member: str, where: str) -> np.ndarray:
    try:
        table = _feather().read_table(io.BytesIO(zf.read(member)))
    except Exception as e:  # pyarrow raises several types
        raise ExportError(f"{where}: mask {member} cannot be read as Feather ({e})") from None
    if table.num_columns != 1:
        raise ExportError(f"{where}: mask {member} has columns {table.column_names}; one bool column expected")
    mask = table.column(0).to_numpy(zero_copy_only=False)
    if mask.dtype != np.bool_:
        raise ExportError(f"{where}: mask {member} is {mask.dtype}, not bool")
    return mask


def _check_sweep(s: _Sweep) -> str | None:
    """Why the run's output cannot give this sweep's submission (None: it can)."""
    info = s.info
    st = info.settings
    if info.points_frame != "native":
        return f"{info.path}: its points were in one world frame ({info.points_frame}), not the sweep's ego frame"
    pose_source = st.get("pose_source")
    log_id = s.member.split("/")[0]
    if st.get("ego_motion") != "table" or not pose_source or Path(pose_source).name != _POSES_FILE \
            or Path(pose_source).parent.name != log_id:
        how = {"identity": "--no-ego-motion", "frame": "poses stored in the frames"}.get(st.get("ego_motion"),
                                                                                      f"poses from {pose_source}")
        return (f"{info.path}: the run compensated ego motion with {how}; the challenge's flow is defined with "
                f"the log's own poses ({log_id}/{_POSES_FILE}): re-run floxels on the log without --poses/"
                f"--odometry/--no-ego-motion")
    if not info.has_ego_motion:
        return f"{info.path}: no 'ego_motion' to the next sweep (the run had no next sweep for this one)"
    if info.step is None or s.period is None or info.step <= 0:
        return f"{info.path}: the time to the next sweep is unknown (no frame times recorded)"
    return None


def _collect(run_dir) -> dict[str, _Sweep]:
    """Every Argoverse 2 sweep RUN has, by its submission name."""
    sweeps: dict[str, _Sweep] = {}
    for seq in find_sequences(run_dir):
        infos, period = sequence_infos(seq)
        for info in infos:
            sid = av2_sweep_id(info)
            if sid is None:
                raise ExportError(f"{info.path}: not the output of an Argoverse 2 sweep (its source "
                                  f"{info.source} is not <log_id>/sensors/lidar/<timestamp_ns>.feather, or it "
                                  f"records no timestamp): --format av2-submission needs a run over Argoverse 2 "
                                  f"logs, which names the log and the sweep times")
            member = f"{sid[0]}/{sid[1]}.feather"
            if member in sweeps:
                raise ExportError(f"{info.path} and {sweeps[member].info.path} are both sweep {member}")
            sweeps[member] = _Sweep(info, period, member)
    return sweeps


def _write_feather(path: Path, flow: np.ndarray, is_dynamic: np.ndarray) -> None:
    import pyarrow as pa

    table = pa.table({"flow_tx_m": flow[:, 0].astype(np.float16), "flow_ty_m": flow[:, 1].astype(np.float16),
                      "flow_tz_m": flow[:, 2].astype(np.float16), "is_dynamic": is_dynamic.astype(bool)})
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        _feather().write_feather(table, str(tmp))
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def _sweep_rows(s: _Sweep, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """(flow (M, 3) float64, is_dynamic (M,), masked points the run did not estimate)."""
    from floxels_ext.lidar.io.outputs import OutputError, read_flow_output

    try:
        out = read_flow_output(s.info.path)
    except OutputError as e:
        raise ExportError(str(e)) from None
    pts, flow = out["points"][mask], out["flow"][mask]
    disp = displacement_to_next(pts, flow, out["ego_motion"], s.info.step / s.period)
    bad = ~np.isfinite(disp).all(1)
    if bad.any():
        raise ExportError(f"{s.info.path}: {int(bad.sum())} point(s) of the mask have NaN/inf coordinates or "
                          f"flow (first: row {int(np.flatnonzero(mask)[np.argmax(bad)])} of the sweep)")
    return disp, out["dynamic"][mask], int((~out["mask"][mask]).sum())


def export_av2_submission(run_dir, out_dir, masks, *, zip_path=None, partial: bool = False, report=print) -> dict:
    """Write OUT/<log_id>/<timestamp_ns>.feather for every sweep of the mask archive and the
    zip (default OUT/submission.zip); returns a summary. :class:`ExportError` before anything
    is written when the run cannot give them (module docstring)."""
    out_dir = Path(out_dir)
    zip_path = Path(zip_path) if zip_path is not None else out_dir / "submission.zip"
    index = read_mask_index(masks)
    sweeps = _collect(run_dir)
    missing = [m for m in index if m not in sweeps]
    if missing and not partial:
        logs = sorted({m.split("/")[0] for m in missing})
        raise ExportError(f"RUN {run_dir} has no output for {len(missing)} of the {len(index)} sweeps that --masks "
                          f"{masks} lists ({len(logs)} log(s), e.g. {missing[0]}); the leaderboard needs every one. "
                          f"Run floxels over those logs, or pass --partial for the sweeps the run has (not a valid "
                          f"submission, but what the evaluation of those sweeps reads)")
    wanted = [m for m in index if m in sweeps]
    if not wanted:
        raise ExportError(f"RUN {run_dir} holds none of the {len(index)} sweeps that --masks {masks} lists "
                          f"(its sweeps: e.g. {next(iter(sweeps))}); is it the same split?")
    problems = [p for m in wanted if (p := _check_sweep(sweeps[m])) is not None]
    if problems:
        more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
        raise ExportError(f"{problems[0]}{more}")
    with zipfile.ZipFile(masks) as zf:
        for m in wanted:  # lengths first (each mask read again below: a split's masks fill GBs)
            n = len(_read_mask(zf, index[m], str(masks)))
            if n != sweeps[m].info.rows:
                raise ExportError(f"mask {m} covers {n} points but the run's sweep has {sweeps[m].info.rows} "
                                  f"({sweeps[m].info.path}): not the same sweep file")
        out_dir.mkdir(parents=True, exist_ok=True)
        if zip_path.exists():
            zip_path.unlink()  # it would describe the files as they were: gone until all are rewritten
        rows = not_estimated = 0
        for m in wanted:
            disp, dyn, left = _sweep_rows(sweeps[m], _read_mask(zf, index[m], str(masks)))
            _write_feather(out_dir / m, disp, dyn)
            rows += len(disp)
            not_estimated += left
    tmp = zip_path.with_name(f".{zip_path.name}.{os.getpid()}.tmp")
    try:
        with zipfile.ZipFile(tmp, "w") as z:
            for m in wanted:  # stored, in the masks' order, as make_submission_archive.zip writes it
                z.write(out_dir / m, arcname=index[m])
        os.replace(tmp, zip_path)
    finally:
        if tmp.exists():
            tmp.unlink()
    summary = {"sweeps": len(wanted), "masked_sweeps": len(index), "logs": len({m.split("/")[0] for m in wanted}),
               "points": rows, "not_estimated": not_estimated, "zip": str(zip_path), "partial": bool(missing)}
    report(f"wrote {len(wanted)} sweep(s) of {summary['logs']} log(s) to {out_dir} and {zip_path}: {rows} points; "
           f"{not_estimated} of them were not estimated by the run (its crop or ground removal) and carry the ego "
           f"motion only")
    if missing:
        print(f"floxels: warning: --partial: {len(missing)} of the {len(index)} sweeps of the masks are not in RUN "
              f"and not in the zip: it is NOT a valid leaderboard submission", file=sys.stderr)
    return summary
