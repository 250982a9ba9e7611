"""Readable bird's-eye views of scene flow with matplotlib (extra ``viz``; headless, Agg).

One figure: the scene in metres (static points grey, moving points coloured by the flow's
direction (hue) and speed (saturation), like the colour wheel beside it, whose radius is
speed), each moving object boxed and numbered, a scale bar; beside the scene, outside the
data, the colour wheel and the key of the numbers (each object's median speed); zoom panels
on the largest moving objects with their flow arrows (ground truth as black outlines when
given); optionally the ground truth's scene beside the estimate. Before (issue 45) the wheel
sat in a corner of the scene, over its points, and the speed labels in the scene overlapped.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from floxels_ext.lidar.io._optional import require

__all__ = ["plot_flow_bev", "flow_figure", "moving_objects", "require_matplotlib"]


def require_matplotlib():
    """matplotlib.pyplot on the Agg backend, or MissingDependencyError saying what to install."""
    mpl = require("matplotlib", "viz", "matplotlib", "drawing flow pictures (PNG)")
    mpl.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _flow_colours(flow_xy: np.ndarray, vmax: float) -> np.ndarray:
    """RGB in [0, 1]: hue = direction of motion, saturation = speed / vmax (white = still)."""
    from matplotlib.colors import hsv_to_rgb

    ang = np.arctan2(flow_xy[:, 1], flow_xy[:, 0])
    hue = (ang / (2 * math.pi)) % 1.0
    sat = np.clip(np.linalg.norm(flow_xy, axis=1) / max(vmax, 1e-9), 0, 1)
    return hsv_to_rgb(np.stack([hue, 0.25 + 0.75 * sat, 0.95 - 0.25 * sat], -1))


def moving_objects(points: np.ndarray, flow: np.ndarray, moving: np.ndarray, cell: float = 1.0,
                   min_points: int = 5) -> list[np.ndarray]:
    """Indices of the moving points grouped into objects (8-connected occupied cells of
    ``cell`` metres in the top view), largest first; groups below ``min_points`` dropped.
    (A top-view grouping for pictures, not the estimator's DBSCAN.)"""
    from scipy import ndimage

    idx = np.flatnonzero(moving)
    if idx.size == 0:
        return []
    xy = points[idx, :2]
    lo = xy.min(0)
    ij = np.floor((xy - lo) / cell).astype(np.int64)
    shape = tuple(ij.max(0) + 1)
    if shape[0] * shape[1] > 50_000_000:  # absurd extent: one object per point cloud half
        return [idx]
    occ = np.zeros(shape, bool)
    occ[ij[:, 0], ij[:, 1]] = True
    lab, n = ndimage.label(occ, structure=np.ones((3, 3)))
    plab = lab[ij[:, 0], ij[:, 1]]
    groups = [idx[plab == k] for k in range(1, n + 1)]
    groups = [g for g in groups if g.size >= min_points]
    return sorted(groups, key=len, reverse=True)


def _scale_bar(ax, span: float) -> None:
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    nice = [1, 2, 5, 10, 20, 50, 100, 200, 500]
    length = max([v for v in nice if v <= span / 4] or [nice[0]])
    ax.add_artist(AnchoredSizeBar(ax.transData, length, f"{length} m", "lower right", pad=0.4,
                                  sep=3, frameon=True, size_vertical=span / 300, color="black"))


def _wheel(ax, vmax_frame: float, to_unit: float, unit: str) -> None:
    """Colour key on the polar axes ``ax``: direction = angle, speed = radius (same mapping as
    the points; ``vmax_frame`` in m/frame, labels in ``unit``)."""
    th, r = np.meshgrid(np.linspace(-math.pi, math.pi, 181), np.linspace(0, vmax_frame, 40))
    vec = np.stack([r.ravel() * np.cos(th.ravel()), r.ravel() * np.sin(th.ravel())], -1)
    rgb = _flow_colours(vec, vmax_frame).reshape(r.shape + (3,))
    ax.pcolormesh(th, r, rgb, shading="nearest", rasterized=True)
    vmax = vmax_frame * to_unit
    ax.set_ylim(0, vmax_frame)
    ax.set_yticks([vmax_frame / 2, vmax_frame])
    ax.set_yticklabels([f"{vmax / 2:.2g}", f"{vmax:.2g}"], fontsize=7)
    ax.set_xticks(np.radians([0, 90, 180, 270]))
    ax.set_xticklabels(["+x", "+y", "-x", "-y"], fontsize=7)
    ax.tick_params(pad=0)
    ax.set_title(f"direction / speed ({unit})", fontsize=8, pad=4)


def _object_key(ax, entries: list[str]) -> None:
    """The numbers of the boxed objects with their median speeds (``entries``), as text on a
    bare axes."""
    ax.axis("off")
    if not entries:
        return
    lines = ["moving objects", "(median speed)"] + [f"{k + 1}: {e}" for k, e in enumerate(entries)]
    ax.text(0.5, 1.0, "\n".join(lines), transform=ax.transAxes, ha="center", va="top", fontsize=8, linespacing=1.5)


def _scene(ax, pts, flow, moving, vmax, view, objects, title, static_mask=None) -> None:
    still = ~moving
    grey = np.where(static_mask[still], 0.55, 0.78) if static_mask is not None else 0.6
    ax.scatter(pts[still, 0], pts[still, 1], s=0.8, c=np.broadcast_to(np.atleast_1d(grey)[:, None] * [1, 1, 1],
                                                                          (int(still.sum()), 3)),
               linewidths=0, rasterized=True)
    if moving.any():
        order = np.flatnonzero(moving)
        ax.scatter(pts[order, 0], pts[order, 1], s=4.0, c=_flow_colours(flow[order, :2], vmax),
                   linewidths=0, rasterized=True)
    boxes, labels = [], []
    for k, g in enumerate(objects):
        lo, hi = pts[g, :2].min(0) - 0.8, pts[g, :2].max(0) + 0.8
        ax.add_patch(_rect(lo, hi))
        boxes.append((lo, hi))
        # the number only (its speed is in the key beside the scene): short labels find free places
        labels.append(ax.text(hi[0], hi[1], f"{k + 1}", fontsize=8, va="bottom", ha="left", clip_on=True,
                              bbox=dict(boxstyle="round,pad=0.15", fc="white", ec="none", alpha=0.8)))
    (x0, x1), (y0, y1) = view
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title, fontsize=10)
    ax.grid(True, lw=0.3, alpha=0.5)
    _scale_bar(ax, min(x1 - x0, y1 - y0))
    ax.apply_aspect()  # the axes' final place, before labels are placed in pixels
    _declutter(ax, labels, boxes)


# label positions tried around an object's box, in order: (corner x, corner y, ha, va); each
# also moved outward by one and two label sizes when every spot next to the box is taken
_LABEL_SPOTS = [("hi", "hi", "left", "bottom"), ("lo", "hi", "right", "bottom"), ("hi", "lo", "left", "top"),
                ("lo", "lo", "right", "top"), ("hi", "mid", "left", "center"), ("lo", "mid", "right", "center"),
                ("mid", "hi", "center", "bottom"), ("mid", "lo", "center", "top")]


def _declutter(ax, labels, boxes) -> None:
    """Move each object's label to the first spot around its box (or one or two label sizes
    further out) where it overlaps no label placed before it, no other object's box and no
    edge of the panel; where none is free, the spot overlapping least (labels count most)."""
    if not labels:
        return
    fig = ax.figure
    renderer = fig.canvas.get_renderer()
    to_px, to_data = ax.transData.transform, ax.transData.inverted().transform
    box_px = [(to_px(lo), to_px(hi)) for lo, hi in boxes]
    a = ax.get_window_extent(renderer)
    frame = ((a.x0, a.y0), (a.x1, a.y1))
    placed = []

    def overlap(a, b) -> float:
        w = min(a[1][0], b[1][0]) - max(a[0][0], b[0][0])
        h = min(a[1][1], b[1][1]) - max(a[0][1], b[0][1])
        return max(w, 0.0) * max(h, 0.0)

    def extent(t):
        e = t.get_window_extent(renderer).expanded(1.1, 1.15)
        return (e.x0, e.y0), (e.x1, e.y1)

    for k, (t, (lo, hi)) in enumerate(zip(labels, boxes)):
        (w, h) = np.subtract(*extent(t)[::-1])
        best = None
        for step in (0, 1, 2):
            for sx, sy, ha, va in _LABEL_SPOTS:
                x = {"lo": lo[0], "hi": hi[0], "mid": (lo[0] + hi[0]) / 2}[sx]
                y = {"lo": lo[1], "hi": hi[1], "mid": (lo[1] + hi[1]) / 2}[sy]
                px = to_px((x, y)) + step * np.array([{"left": w, "right": -w, "center": 0}[ha] if va == "center" else 0,
                                                      {"bottom": h, "top": -h, "center": 0}[va]])
                pos = tuple(to_data(px))
                t.set_position(pos)
                t.set_ha(ha)
                t.set_va(va)
                ext = extent(t)
                area = (ext[1][0] - ext[0][0]) * (ext[1][1] - ext[0][1])
                cost = (10 * sum(overlap(ext, p) for p in placed)
                        + sum(overlap(ext, b) for j, b in enumerate(box_px) if j != k)
                        + 4 * (area - overlap(ext, frame)) + step)  # cut at the edge: worse than a box
                if best is None or cost < best[0]:
                    best = (cost, pos, ha, va, ext)
                if cost <= step:
                    break
            if best[0] <= step:
                break
        _, pos, ha, va, ext = best
        t.set_position(pos)
        t.set_ha(ha)
        t.set_va(va)
        placed.append(ext)


def _rect(lo, hi):
    from matplotlib.patches import Rectangle

    return Rectangle(lo, *(hi - lo), fill=False, ec="black", lw=0.8)


def _zoom(ax, pts, flow, gt, g, k, sp, vmax, unit, to_unit, speed) -> None:
    both = speed if gt is None else np.maximum(speed, np.linalg.norm(gt[:, :2], axis=1))
    arrow_scale = _arrow_scale(g, pts, both)
    tips = [pts[g, :2], pts[g, :2] + arrow_scale * flow[g, :2]]
    if gt is not None:
        tips.append(pts[g, :2] + arrow_scale * gt[g, :2])
    lo, hi = np.min([t.min(0) for t in tips], 0), np.max([t.max(0) for t in tips], 0)
    c, half = (lo + hi) / 2, max((hi - lo).max() / 2 + 1.0, 3.0)
    near = np.flatnonzero(np.all(np.abs(pts[:, :2] - c) <= half * 1.05, axis=1))
    ax.scatter(pts[near, 0], pts[near, 1], s=3, c="0.7", linewidths=0, rasterized=True)
    sub = g[np.linspace(0, g.size - 1, min(g.size, 40)).astype(int)]
    col = _flow_colours(flow[sub, :2], vmax)
    if gt is not None:
        ax.quiver(pts[sub, 0], pts[sub, 1], gt[sub, 0], gt[sub, 1], angles="xy", scale_units="xy",
                  scale=1 / arrow_scale, width=0.012, color="black", alpha=0.45, zorder=2)
    ax.quiver(pts[sub, 0], pts[sub, 1], flow[sub, 0], flow[sub, 1], angles="xy", scale_units="xy",
              scale=1 / arrow_scale, width=0.008, color=col, zorder=3)
    ax.scatter(pts[g, 0], pts[g, 1], s=4, c=_flow_colours(flow[g, :2], vmax), linewidths=0, zorder=1)
    ax.set_xlim(c[0] - half, c[0] + half)
    ax.set_ylim(c[1] - half, c[1] + half)
    ax.set_aspect("equal")
    ax.tick_params(labelsize=7)
    ax.grid(True, lw=0.3, alpha=0.5)
    txt = f"object {k + 1}: {sp:.2g} {unit}"
    if gt is not None:
        txt += f" (true {np.median(np.linalg.norm(gt[g, :2], axis=1)) * to_unit:.2g})"
    ax.set_title(txt, fontsize=8)
    ax.set_xlabel(f"x (m); arrow = {arrow_scale:g} frame{'s' if arrow_scale != 1 else ''}"
                  + ("; black: truth" if gt is not None else ""), fontsize=7)


def plot_flow_bev(path, points, flow, *, gt_flow=None, mask=None, title: str = "",
                  frame_period: float | None = None, min_speed: float = 0.1, view=None,
                  max_zooms: int = 4, dpi: int = 110) -> Path:
    """Write a PNG of ``points`` (N, 3) and their ``flow`` (N, 3, metres per frame): the
    figure of :func:`flow_figure` (same arguments)."""
    plt = require_matplotlib()
    fig = flow_figure(points, flow, gt_flow=gt_flow, mask=mask, title=title, frame_period=frame_period,
                      min_speed=min_speed, view=view, max_zooms=max_zooms, dpi=dpi)
    path = Path(path)
    from floxels_ext.output_paths import replace_atomically

    try:
        return replace_atomically(path.with_name(f".{path.name}.{os.getpid()}.tmp.png"), path,
                                  lambda t: fig.savefig(t, bbox_inches="tight"))
    finally:
        plt.close(fig)


def flow_figure(points, flow, *, gt_flow=None, mask=None, title: str = "", frame_period: float | None = None,
                min_speed: float = 0.1, view=None, max_zooms: int = 4, dpi: int = 110):
    """The matplotlib figure of :func:`plot_flow_bev` (the caller closes it).

    ``gt_flow``: ground truth, drawn beside the estimate and as black arrows in the zooms;
    ``mask``: points that were estimated (others, e.g. ground, drawn lighter); points moving
    more than ``min_speed`` m/frame are "moving"; ``frame_period`` (s) labels speeds in m/s
    (else m/frame); ``view`` ((x0, x1), (y0, y1)) in metres (default: the points' extent).
    Its axes carry labels: ``"scene"`` (and ``"truth"``), ``"wheel"``, ``"key"``, ``"zoom k"``."""
    plt = require_matplotlib()
    pts = np.asarray(points, np.float64)
    flow = np.asarray(flow, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or flow.shape != pts.shape:
        raise ValueError(f"points and flow must both be (N, 3), got {pts.shape} and {flow.shape}")
    ok = np.isfinite(pts).all(1)
    flow = np.where(np.isfinite(flow), flow, 0.0)
    gt = None if gt_flow is None else np.where(np.isfinite(gt_flow), np.asarray(gt_flow, np.float64), 0.0)
    mask = ok if mask is None else (np.asarray(mask, bool) & ok)
    pts, flow, mask = pts[ok], flow[ok], mask[ok]
    gt = None if gt is None else gt[ok]
    to_unit, unit = (1.0 / frame_period, "m/s") if frame_period else (1.0, "m/frame")
    speed = np.linalg.norm(flow[:, :2], axis=1)
    moving = mask & (speed > min_speed)
    # most evident first (points x speed): fast cars before a slowly creeping wall
    objects = sorted(moving_objects(pts, flow, moving), key=lambda g: -g.size * float(np.median(speed[g])))[:9]
    speeds = [float(np.median(speed[g])) * to_unit for g in objects]
    all_speed = [speed[moving]] + ([np.linalg.norm(gt[mask, :2], axis=1)] if gt is not None else [])
    top = max((float(np.percentile(s, 98)) for s in all_speed if s.size), default=1.0)
    vmax_frame = max(top, min_speed * 2)
    if view is None:
        if len(pts):
            lo, hi = np.percentile(pts[:, :2], 0.5, axis=0) - 2, np.percentile(pts[:, :2], 99.5, axis=0) + 2
        else:
            lo, hi = np.array([-10.0, -10.0]), np.array([10.0, 10.0])
        for g in objects:  # every boxed object whole, with room for its label
            lo = np.minimum(lo, pts[g, :2].min(0) - 3.0)
            hi = np.maximum(hi, pts[g, :2].max(0) + 3.0)
        view = ((lo[0], hi[0]), (lo[1], hi[1]))
    zooms = objects[:max_zooms]
    ncols = 2 if gt is not None else 1
    key_w = 1.9  # the column beside the scene(s): colour wheel and object key, outside the data
    if ncols == 2 or not zooms:  # scene(s) and key on top, zooms in a row below
        fig = plt.figure(figsize=(7.5 * ncols + key_w, 7.5 + (2.9 if zooms else 0)), dpi=dpi)
        grid = fig.add_gridspec(2 if zooms else 1, max(len(zooms), 1),
                                height_ratios=[7.5, 2.7] if zooms else None, hspace=0.3)
        top_grid = grid[0, :].subgridspec(1, ncols + 1, wspace=0.15, width_ratios=[7.5] * ncols + [key_w])
        zoom_cells = [grid[1, k] for k in range(len(zooms))]
    else:  # one scene on the left, the key, zooms in a 2 x 2 block on the right
        fig = plt.figure(figsize=(13.5 + key_w, 7.8), dpi=dpi)
        grid = fig.add_gridspec(1, 3, width_ratios=[7.5, key_w, 5.2], wspace=0.12)
        top_grid = grid[0, :2].subgridspec(1, 2, width_ratios=[7.5, key_w], wspace=0.12)
        right = grid[0, 2].subgridspec(2, 2, hspace=0.35, wspace=0.3)
        zoom_cells = [right[k // 2, k % 2] for k in range(len(zooms))]
    key_cells = top_grid[0, ncols].subgridspec(2, 1, height_ratios=[1.0, 1.6], hspace=0.25)
    ax = fig.add_subplot(top_grid[0, 0], label="scene")
    vm = vmax_frame
    # colours are in m/frame internally; the wheel's labels in the display unit
    _scene(ax, pts, flow, moving, vm, view, objects,
           "estimated flow" + (f" ({int(moving.sum())} moving points)" if moving.any() else " (nothing moving)"),
           static_mask=mask)
    key = [f"{sp:.2g} {unit}" for sp in speeds]
    if gt is not None:
        gspeed = np.linalg.norm(gt[:, :2], axis=1)
        gmov = mask & (gspeed > min_speed)
        true = [float(np.median(gspeed[g])) * to_unit for g in objects]
        # the estimate's objects, numbered alike in both panels
        _scene(fig.add_subplot(top_grid[0, 1], sharex=ax, sharey=ax, label="truth"), pts, gt, gmov, vm, view,
               objects, f"ground truth ({int(gmov.sum())} moving points)", static_mask=mask)
        key = [f"{k} (true {t:.2g})" for k, t in zip(key, true)]
    for k, g in enumerate(zooms):
        _zoom(fig.add_subplot(zoom_cells[k], label=f"zoom {k}"), pts, flow, gt, g, k, speeds[k], vm, unit, to_unit,
              speed)
    _wheel(fig.add_subplot(key_cells[0], projection="polar", label="wheel"), vm, to_unit, unit)
    _object_key(fig.add_subplot(key_cells[1], label="key"), key)
    if title:
        fig.suptitle(title, fontsize=11)
    return fig


def _arrow_scale(g, pts, speed) -> float:
    """Arrow length multiplier so the object's arrows span about half its size."""
    size = max(float((pts[g, :2].max(0) - pts[g, :2].min(0)).max()), 2.0) * 2
    fast = max(float(np.median(speed[g])), 1e-6)
    s = size / 4 / fast
    for nice in (1, 2, 3, 5, 10):
        if nice >= s:
            return float(nice)
    return 10.0
