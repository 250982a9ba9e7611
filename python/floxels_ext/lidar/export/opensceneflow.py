"""``floxels export RUN --format opensceneflow OUT``: pseudo-labels in the files OpenSceneFlow's
trainers read as they are (DeFlow, SeFlow, FastFlow3D with ZeroFlow's distillation loss).

Why this format (docs/export.md): it is the one of the three frameworks read for
this (ZeroFlow, SceneFlowZoo, OpenSceneFlow) whose files carry their own points, ground mask and
poses. ZeroFlow's pseudo-labels (``<log>/<index>.npz`` with ``flow`` and ``valid_idxes``) index
into the points left after *its* map-based ground removal of the raw Argoverse 2 files, and
SceneFlowZoo's go through the raw dataset tree as well; OpenSceneFlow's dataloader takes any
scene from its ``.h5`` file, so a run over any lidar (KITTI, AV2, a directory of .pcd) becomes
training data, with the run's own crop and ground removal.

The layout, as read by ``HDF5Dataset`` (KTH-RPL/OpenSceneFlow, commit 848bf86, ``src/dataset.py``)
and written by its ``dataprocess/extract_av2.py`` (``create_group_data``) and
``dataprocess/misc_data.py`` (``create_reading_index``):

* ``OUT/<scene_id>.h5``: one group per frame named by its timestamp (``str`` of an integer:
  the sweep's ns for Argoverse 2, else the frame number of its file name), holding
  ``lidar`` (N, 3) float32 (the frame's points, its own coordinates), ``ground_mask`` (N,) bool
  (points the trainer drops from the frame: here every point the run did not estimate, i.e.
  its ground, its crop and non-finite rows), ``pose`` (4, 4) float32 (the frame's coordinates to
  the scene's; relative to the scene's first frame so that float32 keeps millimetres), and for
  every frame but the last ``flow`` (N, 3) float32 (the run's flow as the dataset's labels are:
  where the point is at the next frame in the next frame's coordinates, minus where it is;
  the trainer subtracts the ego motion it computes from the two poses; points the run did not
  estimate move with the ego motion only), ``flow_is_valid`` (N,) bool (the points the run
  estimated) and ``ego_motion`` (4, 4) float32. No ``flow_category_indices``: pseudo-labels have no
  classes, so train with a loss that needs none (``loss_fn=zeroflowLoss`` or ``deflowLoss``);
* ``OUT/index_total.pkl``: ``[[scene_id, timestamp], ...]`` of every frame, in time order;
  ``OUT/index_flow.pkl``: those with ``flow``.

A scene's frames must be consecutive (the trainer pairs each with the next group): a run with
frames missing in the middle (failed, or left out) is refused, as is a frame without the
ego motion to its next one. Each ``.h5`` is written under a temporary name and renamed; the
index files are written last.
"""

from __future__ import annotations

import os
import pickle
from pathlib import Path

import numpy as np

from floxels_ext.lidar.export.run_frames import ExportError, FrameInfo, RunSequence, displacement_to_next, find_sequences, sequence_infos

__all__ = ["export_opensceneflow", "scene_key"]


def _h5py():
    from floxels_ext.lidar.io._optional import require

    return require("h5py", "opensceneflow", "h5py", "writing OpenSceneFlow .h5 files")


def scene_key(info: FrameInfo) -> str:
    """The group name of a frame: its timestamp in ns (Argoverse 2), else its number."""
    if info.timestamp_ns is not None:
        return str(info.timestamp_ns)
    if info.name.isdigit():
        return str(int(info.name))
    raise ExportError(f"{info.path}: the frame has no timestamp and its name {info.name!r} is not a number; "
                      f"OpenSceneFlow names a scene's frames by integer timestamps")


def _scene_id(seq: RunSequence, infos: list[FrameInfo], run_dir: Path) -> str:
    from floxels_ext.lidar.export.av2_submission import av2_sweep_id

    sid = av2_sweep_id(infos[0])
    if sid is not None:
        return sid[0]
    name = Path(run_dir).resolve().name if seq.rel == "." else seq.rel.replace("/", "_")
    if not name or "." in name:
        raise ExportError(f"{seq.out_dir}: cannot name the scene after {name!r} (the dataloader splits file names "
                          f"at '.'); rename the directory")
    return name


def _plan(seq: RunSequence, run_dir: Path) -> tuple[str, list[FrameInfo], list[str], float | None]:
    """(scene id, frames, their keys, frame period), after every check (module docstring)."""
    infos, period = sequence_infos(seq)
    keys = [scene_key(i) for i in infos]
    if len(set(keys)) != len(keys):
        raise ExportError(f"{seq.out_dir}: two frames share the timestamp {next(k for k in keys if keys.count(k) > 1)}")
    if [int(k) for k in keys] != sorted(int(k) for k in keys):
        raise ExportError(f"{seq.out_dir}: the frames' timestamps are not in the order of their names")
    for a, b in zip(infos, infos[1:]):
        if a.next_name is not None and a.next_name != b.name:
            raise ExportError(f"{seq.out_dir}: frame {a.next_name} (after {a.name}) has no output in the run, but "
                              f"{b.name} has; OpenSceneFlow pairs each frame with the next one stored, so the scene "
                              f"must be complete: re-run the missing frames (floxels run resumes)")
        if a.points_frame == "native" and not a.has_ego_motion:
            raise ExportError(f"{a.path}: no 'ego_motion' to the next frame {b.name} (its pose was unknown)")
    return _scene_id(seq, infos, run_dir), infos, keys, period


def _write_scene(path: Path, infos: list[FrameInfo], keys: list[str], period: float | None) -> int:
    """One scene's .h5 (atomic); returns the number of frames with flow."""
    from floxels_ext.lidar.io.outputs import OutputError, read_flow_output

    h5py = _h5py()
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with_flow = 0
    try:
        with h5py.File(tmp, "w") as f:
            first_inv = None
            for k, (info, key) in enumerate(zip(infos, keys)):
                try:
                    out = read_flow_output(info.path)
                except OutputError as e:
                    raise ExportError(str(e)) from None
                native = info.points_frame == "native"
                pose = out["pose"] if native else np.eye(4)
                if first_inv is None:
                    first_inv = np.linalg.inv(pose)
                g = f.create_group(key)
                g.create_dataset("lidar", data=np.asarray(out["points"], np.float32))
                g.create_dataset("ground_mask", data=~out["mask"])
                g.create_dataset("pose", data=(first_inv @ pose).astype(np.float32))
                if k + 1 == len(infos):
                    break  # the last frame: no next one to flow to
                ego = out["ego_motion"] if native else None
                scale = info.step / period if info.step is not None and period else 1.0
                flow = displacement_to_next(out["points"], out["flow"], ego, scale)
                flow[~np.isfinite(flow).all(1)] = 0.0  # rows of NaN/inf points (in ground_mask): kept finite
                g.create_dataset("flow", data=flow.astype(np.float32))
                g.create_dataset("flow_is_valid", data=out["mask"].copy())
                g.create_dataset("ego_motion", data=(np.eye(4) if ego is None else ego).astype(np.float32))
                with_flow += 1
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return with_flow


def _write_pickle(path: Path, value) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as fh:
            pickle.dump(value, fh)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


class _PlainUnpickler(pickle.Unpickler):
    """Reads lists of [str, str] only: a file in OUT is not trusted to run code (no globals)."""

    def find_class(self, module, name):
        raise pickle.UnpicklingError(f"not an index of scene ids and timestamps ({module}.{name})")


def _kept_entries(out_dir: Path, written: set) -> tuple[list, list, list]:
    """The index entries of scenes an earlier export wrote to ``out_dir`` that this one does not
    rewrite and whose ``.h5`` is still there (total, with flow, scene ids). Why: the trainer
    reads only the scenes the index lists (OpenSceneFlow builds it from every .h5 of the
    directory), and a second export into the same OUT replaced it: the first run's scenes were
    left on disk but silently dropped from training."""
    old = []
    for name in ("index_total.pkl", "index_flow.pkl"):
        try:
            with open(out_dir / name, "rb") as fh:
                entries = _PlainUnpickler(fh).load()
            old.append([e for e in entries if e[0] not in written and (out_dir / f"{e[0]}.h5").is_file()])
        except (OSError, EOFError, pickle.UnpicklingError, TypeError, IndexError, AttributeError):
            old.append([])  # none, or not an index of ours: written afresh as before
    return old[0], old[1], list(dict.fromkeys(e[0] for e in old[0]))


def export_opensceneflow(run_dir, out_dir, *, report=print) -> dict:
    """Write OUT/<scene_id>.h5 per sequence of RUN and OUT/index_total.pkl, index_flow.pkl;
    returns a summary. Every sequence is checked before anything is written."""
    _h5py()
    run_dir, out_dir = Path(run_dir), Path(out_dir)
    plans = [_plan(seq, run_dir) for seq in find_sequences(run_dir)]
    ids = [p[0] for p in plans]
    if len(set(ids)) != len(ids):
        raise ExportError(f"two sequences of RUN {run_dir} would both be scene {next(i for i in ids if ids.count(i) > 1)}")
    out_dir.mkdir(parents=True, exist_ok=True)
    total, with_flow, frames = [], [], 0
    for scene, infos, keys, period in plans:
        n = _write_scene(out_dir / f"{scene}.h5", infos, keys, period)
        total += [[scene, k] for k in keys]
        with_flow += [[scene, k] for k in keys[:n]]
        frames += len(keys)
    kept = _kept_entries(out_dir, set(ids))
    _write_pickle(out_dir / "index_total.pkl", kept[0] + total)
    _write_pickle(out_dir / "index_flow.pkl", kept[1] + with_flow)
    report(f"wrote {len(plans)} scene(s), {frames} frames ({len(with_flow)} with flow) to {out_dir} "
           f"(OpenSceneFlow .h5 + index_total.pkl, index_flow.pkl)")
    if kept[2]:
        report(f"the index files also keep the {len(kept[2])} scene(s) already in {out_dir}: {', '.join(kept[2])}")
    return {"scenes": len(plans), "frames": frames, "with_flow": len(with_flow), "out": str(out_dir)}
