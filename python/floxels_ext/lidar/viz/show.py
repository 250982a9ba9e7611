"""``floxels show``: bird's-eye view of one ``floxels run`` output, and optionally a rerun
recording (``pip install 'floxels_ext[viz]'``).

With matplotlib (extra ``viz``) the picture is :func:`floxels_ext.lidar.viz.flow_plot.plot_flow_bev`:
metres on the axes, a scale bar, moving points coloured by direction and speed (colour
wheel beside the scene), moving objects boxed and numbered (their speeds in a key under the
wheel), zoom panels on them. Without matplotlib a plain raster (:func:`render_frame`) is
written instead: optimised points coloured by height, the others dim grey, flow arrows whose
hue is the heading (wheel in a strip right of the view, outside the data) and brightness the
speed.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

# numpy is imported inside the functions: `floxels --help` loads this module for its parser and
# must stay fast (cli.py: subcommand modules keep their top-level imports light)

__all__ = ["add_parser", "run", "render_frame", "direction_wheel"]


def direction_wheel(img: np.ndarray, radius: int = 28, margin: int = 8) -> np.ndarray:
    """Draw the heading colour legend (same mapping as ``viz.bev_image``) in the top-right corner."""
    import numpy as np

    from floxels_ext.lidar.viz.bev_png import hsv_to_rgb

    h, w, _ = img.shape
    r = min(radius, (min(h, w) - 2 * margin) // 2)
    if r < 4:
        return img
    cy, cx = margin + r, w - margin - r
    yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
    inside = (xx ** 2 + yy ** 2 <= r * r) & (xx ** 2 + yy ** 2 >= (0.35 * r) ** 2)
    # image rows grow downwards: a vector pointing 'up' in the picture has +y in the world
    hue = (np.arctan2(-yy, xx) + math.pi) / (2 * math.pi)
    rgb = (hsv_to_rgb(hue, np.ones_like(hue), np.ones_like(hue)) * 255).astype(np.uint8)
    patch = img[cy - r:cy + r + 1, cx - r:cx + r + 1]
    patch[inside] = rgb[inside]
    return img


def render_frame(data: dict, *, extent: float = 40.0, resolution: float = 0.1, center=None,
                 flow_scale: float = 1.0, legend: bool = True) -> np.ndarray:
    """(H, W, 3) uint8 BEV image of a run output (keys points, flow, mask); with ``legend`` the
    heading wheel is in a strip of 72 columns right of the view."""
    import numpy as np

    from floxels_ext.lidar.viz.bev_png import BACKGROUND, bev_image

    pts = np.asarray(data["points"], np.float64)
    ok = np.isfinite(pts).all(1)
    flow = np.nan_to_num(np.asarray(data["flow"], np.float64))
    if center is None:
        center = _default_center(pts)
    mask = np.asarray(data.get("mask", ok), bool) & ok
    kw = dict(center=center, extent=extent, resolution=resolution)
    # optimised points coloured by height with their flow; the rest (ground, cropped) dim grey below
    img = bev_image(pts[mask], flow[mask], flow_scale=flow_scale, **kw)
    rest = bev_image(pts[ok & ~mask], color_by="grey", **kw)
    empty = np.all(img == BACKGROUND, axis=2) & ~np.all(rest == BACKGROUND, axis=2)
    img[empty] = (0.45 * rest[empty] + 0.55 * np.array(BACKGROUND)).astype(np.uint8)
    if not legend:
        return img
    # the wheel in a strip of its own right of the view, not over its top right corner
    strip = np.empty((img.shape[0], 2 * 28 + 2 * 8, 3), np.uint8)
    strip[:] = BACKGROUND
    return direction_wheel(np.concatenate([img, strip], axis=1))


def _default_center(points) -> tuple[float, float]:
    """The sensor (origin) when the points surround it, else the points' median."""
    import numpy as np

    pts = np.asarray(points, np.float64)
    ok = np.isfinite(pts).all(1)
    if not ok.any():
        return (0.0, 0.0)
    lo, hi = pts[ok, :2].min(0), pts[ok, :2].max(0)
    if np.all(lo <= 0) and np.all(hi >= 0):
        return (0.0, 0.0)
    m = np.median(pts[ok, :2], 0)
    return (float(m[0]), float(m[1]))


def add_parser(sub) -> None:
    p = sub.add_parser("show", help="bird's-eye-view PNG (and rerun recording) of a frame's points and flow",
                       description="Render one output of 'floxels run' (a .npz file, or RUN_DIR with --frame) as a "
                                   "bird's-eye-view PNG. With matplotlib (pip install 'floxels_ext[viz]'): metres on "
                                   "the axes and a scale bar, moving points coloured by direction (hue) and speed "
                                   "(saturation; colour wheel beside the scene), each moving object boxed and numbered "
                                   "(median speeds in a key under the wheel), zoom panels with flow arrows on the largest ones, ground and cropped points "
                                   "grey. Without matplotlib: a plain raster (points coloured by height, flow arrows "
                                   "coloured by direction, legend wheel in a strip on the right), sized by --extent/--resolution "
                                   "and with arrows scaled by --flow-scale.")
    p.add_argument("target", metavar="FRAME_NPZ_OR_RUN_DIR")
    p.add_argument("--frame", default=None, help="with a RUN_DIR: the frame's name (e.g. 000042) or its index among "
                   "the run's input frames, as floxels run --frames counts them (default: the first output)")
    p.add_argument("--png", metavar="FILE", help="output PNG (default <frame name>.png in the current directory)")
    from floxels_ext.cli_types import positive_float

    p.add_argument("--extent", type=positive_float, default=40.0, help="half-width of the view in metres (default 40)")
    p.add_argument("--resolution", type=positive_float, default=0.1,
                   help="metres per pixel of the plain raster (default 0.1; the matplotlib picture has its own size)")
    p.add_argument("--center", help="X,Y view centre (default: the sensor, else the points' median)")
    p.add_argument("--flow-scale", type=positive_float, default=None,
                   help="plain raster only: arrow length = flow x this (default 1); the matplotlib picture "
                        "scales its zoom arrows to each object")
    p.add_argument("--frame-period", type=positive_float, default=None, metavar="S",
                   help="seconds between frames, to label speeds in m/s (default: m/frame)")
    p.add_argument("--rerun", metavar="FILE.rrd", help="also save a rerun recording (needs rerun-sdk)")
    p.set_defaults(func=run)


def _resolve(target: str, frame: str | None) -> Path:
    from floxels_ext.errors import CLIError
    from floxels_ext.lidar.viz.run_frames import RunFrames

    t = Path(target)
    if t.is_file():
        if frame is not None:
            raise CLIError(f"--frame picks a frame of a RUN_DIR; {t} is one output file")
        return t
    if not t.is_dir():
        raise CLIError(f"{t} does not exist")
    run = RunFrames(t)
    return run.path(run.pick(frame))


def write_rerun(path: Path, data: dict, name: str) -> None:
    import numpy as np

    from floxels_ext.lidar.io._optional import require

    rr = require("rerun", "viz", "rerun-sdk", "writing rerun recordings (--rerun)")
    pts = np.asarray(data["points"], np.float32)
    ok = np.isfinite(pts).all(1)
    flow = np.nan_to_num(np.asarray(data["flow"], np.float32))
    mask = np.asarray(data.get("mask", ok), bool) & ok
    rr.init("floxels", spawn=False)
    rr.save(str(path))
    grey = np.array([150, 150, 150], np.uint8)
    colours = np.where(mask[ok, None], np.array([90, 200, 250], np.uint8), grey)
    rr.log(f"{name}/points", rr.Points3D(pts[ok], colors=colours, radii=0.03))
    moving = mask & (np.linalg.norm(flow, axis=1) > 0.05)
    if moving.any():
        v = flow[moving]
        hue = (np.arctan2(v[:, 1], v[:, 0]) + math.pi) / (2 * math.pi)
        from floxels_ext.lidar.viz.bev_png import hsv_to_rgb

        rgb = (hsv_to_rgb(hue, np.ones_like(hue), np.ones_like(hue)) * 255).astype(np.uint8)
        rr.log(f"{name}/flow", rr.Arrows3D(origins=pts[moving], vectors=v, colors=rgb))


def load_flow_output(path: Path) -> dict:
    """One ``floxels run`` output (:func:`floxels_ext.lidar.io.outputs.read_flow_output`: ``points``,
    ``flow``, ``mask``, ``dynamic``, ...); anything else is a CLIError saying the file is not a
    floxels flow output and why."""
    from floxels_ext.errors import CLIError
    from floxels_ext.lidar.io.outputs import OutputError, SourceError, read_flow_output

    path = Path(path)
    not_output = f"{path}: not a floxels flow output (expected a .npz written by 'floxels run'"
    with open(path, "rb") as f:
        magic = f.read(4)
    if path.suffix.lower() != ".npz":
        raise CLIError(f"{not_output}; this is a {path.suffix or 'suffix-less'} file)")
    if magic[:2] != b"PK":
        raise CLIError(f"{not_output}; this file is not a .npz (zip) archive)")
    try:
        return read_flow_output(path)
    except SourceError as e:  # a floxels output whose input file went missing or changed
        raise CLIError(str(e)) from None
    except OutputError as e:
        raise CLIError(f"{not_output}): {e}") from None


def run(args: argparse.Namespace) -> int:
    from floxels_ext.errors import CLIError
    from floxels_ext.lidar.io import MissingDependencyError
    from floxels_ext.lidar.viz.bev_png import write_png
    from floxels_ext.output_paths import check_output_file

    path = _resolve(args.target, args.frame)
    data = load_flow_output(path)
    center = None
    if args.center:
        try:
            center = tuple(float(v) for v in args.center.split(","))
            assert len(center) == 2 and all(math.isfinite(v) for v in center)
        except (ValueError, AssertionError):
            raise CLIError(f"--center expects X,Y (two finite numbers), got {args.center!r}") from None
    if not (args.extent > 0 and args.resolution > 0) or args.extent / args.resolution > 8000:
        raise CLIError("--extent and --resolution must be > 0 and give at most 16000 pixels across")
    if args.frame_period is not None and not args.frame_period > 0:
        raise CLIError(f"--frame-period must be > 0 seconds, got {args.frame_period}")
    png = check_output_file(args.png if args.png else f"{path.stem}.png", "--png", f"{path.stem}.png", suffix=".png")
    rerun = None
    if args.rerun:  # before the picture: a missing package or place must not leave half the output
        from floxels_ext.lidar.io._optional import require

        rerun = check_output_file(args.rerun, "--rerun", f"{path.stem}.rrd")
        try:
            require("rerun", "viz", "rerun-sdk", "writing rerun recordings (--rerun)")
        except MissingDependencyError as e:
            raise CLIError(str(e)) from None
    n_mov = int(data["dynamic"].sum())
    try:
        from floxels_ext.lidar.viz.flow_plot import plot_flow_bev

        if center is None:
            center = _default_center(data["points"])
        view = ((center[0] - args.extent, center[0] + args.extent), (center[1] - args.extent, center[1] + args.extent))
        plot_flow_bev(png, data["points"], data["flow"], mask=data["mask"], view=view,
                      frame_period=args.frame_period, title=f"floxels show: {path}")
        size = "matplotlib"
        if args.flow_scale is not None:
            print("note: --flow-scale applies to the plain raster only; the matplotlib picture scales its arrows "
                  "to each object")
    except MissingDependencyError as e:
        print(f"note: {e}; writing a plain raster instead")
        img = render_frame(data, extent=args.extent, resolution=args.resolution, center=center,
                           flow_scale=1.0 if args.flow_scale is None else args.flow_scale)
        write_png(png, img)
        size = f"{img.shape[1]}x{img.shape[0]}"
    print(f"wrote {png} (frame {path.stem}, {size}, {len(data['points'])} points, {n_mov} moving)")
    if rerun is not None:
        write_rerun(rerun, data, path.stem)
        print(f"wrote {rerun}")
    return 0
