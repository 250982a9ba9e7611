"""Bird's-eye-view PNGs of point clouds and scene flow, with numpy and zlib only.

No matplotlib: points are rasterised into an RGB array and written by a tiny PNG encoder
(8-bit RGB, filter type 0 per row, one zlib-compressed IDAT chunk).
"""

from __future__ import annotations

import math
import os
import struct
import zlib
from pathlib import Path

import numpy as np

__all__ = ["bev_image", "bev_png", "write_png", "hsv_to_rgb"]

BACKGROUND = (12, 12, 16)
GREY = (150, 150, 150)
RED = (235, 50, 50)
# height colour ramp (dark blue -> teal -> green -> yellow), sampled at 0, 1/3, 2/3, 1
_RAMP = np.array([[40, 60, 160], [30, 150, 160], [90, 200, 80], [250, 230, 60]], dtype=np.float64)


def write_png(path: str | os.PathLike, rgb: np.ndarray) -> Path:
    """Write an (H, W, 3) uint8 image as PNG (atomically)."""
    rgb = np.ascontiguousarray(rgb, dtype=np.uint8)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.shape[0] < 1 or rgb.shape[1] < 1:
        raise ValueError(f"image must have shape (H, W, 3) with H, W >= 1, got {rgb.shape}")
    h, w, _ = rgb.shape
    raw = np.concatenate([np.zeros((h, 1), np.uint8), rgb.reshape(h, w * 3)], axis=1).tobytes()

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    png = (b"\x89PNG\r\n\x1a\n"
           + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))  # 8-bit RGB, no interlace
           + chunk(b"IDAT", zlib.compress(raw, 6))
           + chunk(b"IEND", b""))
    path = Path(path)
    from floxels_ext.output_paths import replace_atomically

    return replace_atomically(path.with_name(f".{path.name}.{os.getpid()}.tmp"), path, lambda t: t.write_bytes(png))


def hsv_to_rgb(h: np.ndarray, s: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Vectorised HSV (all in [0, 1]) to RGB in [0, 1], shape (..., 3)."""
    h = np.asarray(h, np.float64) % 1.0
    s, v = np.broadcast_to(s, h.shape), np.broadcast_to(v, h.shape)
    i = np.floor(h * 6).astype(int) % 6
    f = h * 6 - np.floor(h * 6)
    p, q, t = v * (1 - s), v * (1 - f * s), v * (1 - (1 - f) * s)
    table = np.stack([np.stack(c, -1) for c in ((v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q))])
    return np.take_along_axis(table, i[None, ..., None].repeat(3, -1), 0)[0]


def _ramp(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0, 1) * (len(_RAMP) - 1)
    return np.stack([np.interp(x, np.arange(len(_RAMP)), _RAMP[:, c]) for c in range(3)], -1)


def bev_image(points, flow=None, points2=None, *, center=None, extent: float = 40.0, resolution: float = 0.1,
              color_by: str = "height", z_range=(-0.3, 4.0), min_flow: float = 0.05, max_flow: float | None = None,
              flow_scale: float = 1.0, max_arrows: int = 5000) -> np.ndarray:
    """Render a top view (x right, y up) as an (H, W, 3) uint8 array.

    ``points`` (N,3) are grey (``color_by="grey"``) or coloured by height over ``z_range``;
    ``points2`` (e.g. the next scan) are drawn in red underneath; for points with
    ``|flow| > min_flow`` a segment from p to p + flow_scale * flow is drawn, its hue the
    heading and its brightness the magnitude (relative to ``max_flow``, default the largest
    drawn). The view covers ``center +- extent`` metres (default centre: median of points).
    """
    points = np.asarray(points, np.float64).reshape(-1, 3)
    if center is None:
        center = np.median(points[:, :2], axis=0) if len(points) else np.zeros(2)
    cx, cy = float(center[0]), float(center[1])
    size = max(1, int(round(2 * extent / resolution)))
    img = np.empty((size, size, 3), np.uint8)
    img[:] = BACKGROUND

    def to_px(xy):
        col = np.floor((xy[:, 0] - (cx - extent)) / resolution).astype(np.int64)
        row = np.floor(((cy + extent) - xy[:, 1]) / resolution).astype(np.int64)
        ok = (col >= 0) & (col < size) & (row >= 0) & (row < size)
        return row, col, ok

    if points2 is not None:  # drawn first: red shows only where the second scan differs
        p2 = np.asarray(points2, np.float64).reshape(-1, 3)
        row, col, ok = to_px(p2)
        img[row[ok], col[ok]] = RED
    if len(points):
        row, col, ok = to_px(points)
        if color_by == "height":
            order = np.argsort(points[ok, 2])  # higher points drawn last, so they stay visible
            lo, hi = z_range
            colours = _ramp((points[ok, 2][order] - lo) / (hi - lo)).astype(np.uint8)
            img[row[ok][order], col[ok][order]] = colours
        elif color_by == "grey":
            img[row[ok], col[ok]] = GREY
        else:
            raise ValueError(f"color_by must be 'height' or 'grey', got {color_by!r}")
    if flow is not None:
        flow = np.asarray(flow, np.float64)
        if flow.shape != points.shape:
            raise ValueError(f"flow has shape {flow.shape} but points {points.shape}")
        mag = np.linalg.norm(flow[:, :2], axis=1)
        idx = np.flatnonzero(mag > min_flow)
        if idx.size > max_arrows:
            idx = idx[np.linspace(0, idx.size - 1, max_arrows).astype(np.int64)]
        if idx.size:
            start, vec, m = points[idx, :2], flow[idx, :2] * flow_scale, mag[idx]
            top = max_flow if max_flow else float(m.max())
            hue = (np.arctan2(vec[:, 1], vec[:, 0]) + math.pi) / (2 * math.pi)
            val = 0.35 + 0.65 * np.clip(m / top, 0, 1)
            rgb = (hsv_to_rgb(hue, np.ones_like(hue), val) * 255).astype(np.uint8)
            steps = int(min(np.ceil(np.linalg.norm(vec, axis=1).max() / resolution), 4 * size)) + 1
            frac = np.linspace(0, 1, steps + 1)
            seg = start[:, None, :] + frac[None, :, None] * vec[:, None, :]  # (M, steps+1, 2)
            row, col, ok = to_px(seg.reshape(-1, 2))
            colours = np.repeat(rgb, steps + 1, axis=0)
            img[row[ok], col[ok]] = colours[ok]
    return img


def bev_png(path: str | os.PathLike, points, flow=None, points2=None, **kwargs) -> Path:
    """Write ``bev_image(points, flow, points2, **kwargs)`` to ``path`` as PNG."""
    return write_png(path, bev_image(points, flow, points2, **kwargs))
