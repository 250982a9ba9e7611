"""Point-cloud densification with estimated flow (the paper's Fig. "Point cloud densification":
five adjacent scans t-2 .. t+2 moved to time t and merged).

Each scan k has its own estimated flow f_k (motion to the next frame, per frame step). Two
ways to bring scan k to the reference time r:

* ``"constant-velocity"`` (default): ``p + (r - k) * f_k(p)``. Floxels itself fits one
  constant-velocity flow per target over its window (the loss moves support scan t by
  ``t * f``), so this is the motion model the flow was estimated under; it also moves scans
  *after* r backwards without having to invert a flow field.
* ``"chain"``: compose the per-frame flows through the intermediate scans: forward steps take
  the flow of the nearest point of each intermediate scan (within ``radius``, else the last
  one used); backward steps invert f_j by matching against scan j moved by its flow. Better for
  accelerating or turning objects when every frame has flow, noisier where scans are sparse.

Points of every scan must be in ONE frame (pass world coordinates); see
:func:`accumulate_run` for reading ``floxels run`` outputs.
"""

from __future__ import annotations

import argparse
from pathlib import Path

# numpy is imported inside the functions: `floxels --help` loads this module for its parser and
# must stay fast (cli.py: subcommand modules keep their top-level imports light)

__all__ = ["accumulate", "accumulate_run", "add_parser", "run"]


def _nearest_flow(src_pts: np.ndarray, src_flow: np.ndarray, query: np.ndarray, radius: float,
                  fallback: np.ndarray) -> np.ndarray:
    import numpy as np
    from scipy.spatial import cKDTree

    if len(src_pts) == 0:
        return fallback
    d, j = cKDTree(src_pts).query(query, distance_upper_bound=radius)
    ok = np.isfinite(d)
    out = fallback.copy()
    out[ok] = src_flow[j[ok]]
    return out


def accumulate(points: list, flows: list, reference: int, *, mode: str = "constant-velocity",
               radius: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Move every scan to the time of ``points[reference]`` and merge them.

    ``points[k]``, ``flows[k]``: (N_k, 3) in one common frame (``flows[k]`` may be None for the
    reference scan, which is not moved). Non-finite rows are dropped. Returns (M, 3) float32
    points and (M,) int32 index of the scan each came from."""
    import numpy as np

    if mode not in ("constant-velocity", "chain"):
        raise ValueError(f"mode must be 'constant-velocity' or 'chain', got {mode!r}")
    if len(points) != len(flows):
        raise ValueError(f"{len(points)} scans but {len(flows)} flows")
    if not 0 <= reference < len(points):
        raise IndexError(f"reference {reference} out of range for {len(points)} scans")
    P = [np.asarray(p, np.float64).reshape(-1, 3) for p in points]
    F = [None if f is None else np.asarray(f, np.float64).reshape(-1, 3) for f in flows]
    for k, (p, f) in enumerate(zip(P, F)):
        if f is not None and f.shape != p.shape:
            raise ValueError(f"scan {k}: flow has shape {f.shape} but points {p.shape}")
        if f is None and k != reference:
            raise ValueError(f"scan {k} needs a flow to be moved to the reference time")
    ok = [np.isfinite(p).all(1) & (np.isfinite(f).all(1) if f is not None else True) for p, f in zip(P, F)]
    out_p, out_k = [], []
    for k in range(len(P)):
        p = P[k][ok[k]]
        if k == reference or len(p) == 0:
            moved = p
        elif mode == "constant-velocity":
            moved = p + (reference - k) * F[k][ok[k]]
        elif k < reference:
            moved, step = p.copy(), F[k][ok[k]]
            for j in range(k, reference):
                if j > k:
                    step = _nearest_flow(P[j][ok[j]], F[j][ok[j]], moved, radius, step)
                moved = moved + step
        else:
            moved, step = p.copy(), np.zeros_like(p)
            for j in range(k - 1, reference - 1, -1):
                # which point q of scan j lands (q + f_j(q)) nearest to ours: undo its motion
                src = P[j][ok[j]]
                step = _nearest_flow(src + F[j][ok[j]], F[j][ok[j]], moved, radius, step)
                moved = moved - step
        out_p.append(moved)
        out_k.append(np.full(len(moved), k, np.int32))
    return np.concatenate(out_p).astype(np.float32), np.concatenate(out_k)


def load_run_frame(path: Path) -> dict:
    """One ``floxels run`` output (:func:`floxels_ext.lidar.io.outputs.read_flow_output`, points included:
    stored or read back from the source file); errors name the file."""
    from floxels_ext.errors import CLIError
    from floxels_ext.lidar.io.outputs import OutputError, read_flow_output

    try:
        return read_flow_output(path)
    except OutputError as e:
        raise CLIError(str(e)) from None


def accumulate_run(run_dir, frame: int | str, *, neighbours: int = 2, mode: str = "constant-velocity",
                   mask_only: bool = False, radius: float = 1.0, use_flow: bool = True, note=print):
    """Densify frame ``frame`` (its name, or its index among the run's input frames:
    :mod:`floxels_ext.lidar.viz.run_frames`) of a ``floxels run`` output directory with the
    outputs of the ``neighbours`` frames on each side (``use_flow=False``: ego-motion
    compensation only, the 'before' picture). A neighbour without output is left out (``note``
    says which); the others keep their true time offsets. Returns (points (M,3) in the
    reference frame's coordinates, time offset (M,) int32, frame names used)."""
    import numpy as np

    from floxels_ext.lidar.viz.run_frames import RunFrames

    run = RunFrames(run_dir)
    ref = run.pick(frame, note=note)
    around, missing = run.neighbours(ref, neighbours)
    if missing:
        note(f"note: left out {', '.join(missing)}: no output (failed or not estimated)")
    if run.inputs() is None:
        note("note: the run's input frames cannot be listed; neighbours are the adjacent outputs")
    data = {off: load_run_frame(run.path(name)) for off, name in around if name is not None}
    ref_pose = data[0]["pose"]
    offsets = [off for off, _ in around]
    pts_w, flow_w = [], []
    for off in offsets:  # a frame without output: an empty scan at its time (nothing to move)
        d = data.get(off)
        if d is None:
            pts_w.append(np.zeros((0, 3)))
            flow_w.append(np.zeros((0, 3)))
            continue
        T = np.linalg.solve(ref_pose, d["pose"])  # this frame's coordinates -> the reference's
        keep = d["mask"].astype(bool) if mask_only else np.ones(len(d["points"]), bool)
        p = d["points"][keep].astype(np.float64)
        pts_w.append(p @ T[:3, :3].T + T[:3, 3])
        flow_w.append(d["flow"][keep].astype(np.float64) @ T[:3, :3].T * (1.0 if use_flow else 0.0))
    pts, src = accumulate(pts_w, flow_w, offsets.index(0), mode=mode, radius=radius)
    return pts, np.asarray(offsets, np.int32)[src], [name for _, name in around if name is not None]


# ----------------------------------------------------------------------------- CLI
def add_parser(sub) -> None:
    p = sub.add_parser("accumulate", help="densify a frame with its neighbours moved by the estimated flow (.ply)",
                       description="Move the neighbouring scans of a frame to its time with the flow written by "
                                   "'floxels run' and write the merged cloud as binary PLY (properties: x y z, "
                                   "time_offset (frame - reference), red green blue by time offset).")
    p.add_argument("run_dir", metavar="RUN_DIR", help="an OUT_DIR of 'floxels run'")
    p.add_argument("frame", metavar="FRAME", help="frame name (e.g. 000042) or its index among the run's input "
                   "frames (as floxels run --frames counts them)")
    p.add_argument("--out", required=True, metavar="FILE.ply")
    p.add_argument("--neighbours", type=int, default=2, help="scans on each side (default 2: t-2 .. t+2; at most 127)")
    p.add_argument("--mode", choices=["constant-velocity", "chain"], default="constant-velocity")
    p.add_argument("--mask-only", action="store_true", help="only points that were optimised (no ground/far)")
    from floxels_ext.cli_types import positive_float

    p.add_argument("--radius", type=positive_float, default=None,
                   help="m, neighbour search radius of --mode chain (default 1)")
    p.add_argument("--no-flow", action="store_true", help="merge without moving (for comparison)")
    p.set_defaults(func=run)


# colour of each time offset: 0, +1, -1, +2, -2, ... (more distant ones share the last)
_OFFSET_COLOURS = ((255, 255, 255), (240, 80, 60), (60, 160, 250), (250, 190, 40), (90, 210, 120),
                   (200, 100, 230), (120, 220, 220))


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from floxels_ext.errors import CLIError
    from floxels_ext.lidar.io.writers import write_ply

    if not 1 <= args.neighbours <= 127:  # time_offset is an int8 property: more would wrap around
        raise CLIError(f"--neighbours must be in [1, 127], got {args.neighbours}")
    if args.no_flow and (args.mode == "chain" or args.radius is not None):
        raise CLIError("--no-flow merges without moving; --mode chain and --radius do not apply")
    if args.radius is not None and args.mode != "chain":
        raise CLIError("--radius is the neighbour search radius of --mode chain; it does not apply to "
                       "--mode constant-velocity")
    from floxels_ext.output_paths import check_output_file

    out = check_output_file(args.out, "--out", "dense.ply")
    pts, off, names = accumulate_run(args.run_dir, args.frame, neighbours=args.neighbours, mode=args.mode,
                                     mask_only=args.mask_only, radius=args.radius or 1.0, use_flow=not args.no_flow)
    rgb = np.array(_OFFSET_COLOURS, np.uint8)[np.minimum(np.abs(off) * 2 - (off < 0), len(_OFFSET_COLOURS) - 1)]
    write_ply(out, pts, time_offset=off.astype(np.int8), red=rgb[:, 0], green=rgb[:, 1], blue=rgb[:, 2])
    print(f"wrote {out}: {len(pts)} points from frames {names[0]}..{names[-1]} "
          f"({'no motion' if args.no_flow else args.mode})")
    return 0
