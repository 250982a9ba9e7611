"""The checks ``floxels run`` makes on each frame it prepares (``frame_loader.load_frame``): the
rows with finite coordinates, why a frame has no point left after cropping (with the likely
mistake), a few points so far from the rest of a scan that its distance transforms blow up,
float32 coordinates so far out that they lost their precision in the file, no ground within the
ground grid's reach (issue 45); and whether an estimated frame may be written
(:func:`frame_failure`, at the engine's delivery point, ``dataset/stream``).

A frame is not written, and fails with the reason, when the method says it has no estimate
(``fields["failure"]``: Floxels' optimisation diverged) or when none of its support scans
(``Method.support_frames``: Floxels' window, a baseline's pair) could be read: the method then
saw empty scans beside its target and answered zero flow, which was written as "all static"
(``--scans 2`` with the next frame's file broken: 0 moving points instead of 2,652; issue 45).
"""

from __future__ import annotations

import numpy as np

__all__ = ["finite_mask", "empty_crop_message", "far_outliers", "STRAY_DT_BYTES", "STRAY_SPAN", "frame_failure",
           "float32_far_message", "beyond_ground_grid", "FLOAT32_FAR"]

# A support scan's distance transform at the Floxels defaults (0.1 m cells, 2 m padding, float32)
# over the axis-aligned extent of its points: a few stray returns far from the rest (--max-range
# none) multiply it (one point 1 km away: 5.6 GB instead of 0.79 GB). Warned about above this
# size when the scan's bulk alone would need a quarter of it or less.
STRAY_DT_BYTES = 1e9
STRAY_SPAN = 150.0  # m: scans whose coordinates all lie within this span are not examined further


def _dt_bytes(lo, hi, cell: float = 0.1, padding: float = 2.0) -> float:
    return 4.0 * float(np.prod((np.asarray(hi, np.float64) - lo + 2 * padding) / cell + 1))


def far_outliers(kept: np.ndarray) -> str | None:
    """A warning when a few points far from the rest of a scan blow up its distance transform
    (see ``STRAY_DT_BYTES``), else None. Cheap: bounds of all points, quantiles of a sample."""
    if len(kept) < 100:
        return None
    flat = kept.reshape(-1)  # one contiguous pass (per-column reductions cost ~100x more)
    if float(flat.max()) - float(flat.min()) < STRAY_SPAN:  # every axis spans less: nothing to find
        return None
    lo = np.array([kept[:, k].min() for k in range(3)], np.float64)
    hi = np.array([kept[:, k].max() for k in range(3)], np.float64)
    full = _dt_bytes(lo, hi)
    if full < STRAY_DT_BYTES:
        return None
    sample = kept[::max(1, len(kept) // 4096)].astype(np.float64)
    blo = np.maximum(np.percentile(sample, 0.5, axis=0) - 10.0, lo)  # the bulk, 10 m margin
    bhi = np.minimum(np.percentile(sample, 99.5, axis=0) + 10.0, hi)
    bulk = _dt_bytes(blo, bhi)
    if full < 4 * bulk:
        return None
    far = int(((kept < blo - 50.0) | (kept > bhi + 50.0)).any(axis=1).sum())  # clearly apart from the bulk
    dims = lambda a, b: " x ".join(f"{v:.0f}" for v in b - a)  # noqa: E731
    return (f"{far} point(s) lie far outside the rest of the scan (it spans {dims(lo, hi)} m, its bulk "
            f"{dims(blo, bhi)} m): each distance transform of it needs ~{full / 1e9:.1f} GB instead of "
            f"~{bulk / 1e9:.2f} GB (and more time); if they are stray returns, crop them (--max-range, --max-height)")


def empty_crop_message(path, pts_sensor: np.ndarray, settings, pose_mode: str) -> str:
    """Why a frame with finite points has none left after cropping and ground removal, with
    the likely mistake: points not in the frame the ranges are measured in (the sensor at the
    origin), or a crop that removes the whole scan."""
    p = np.asarray(pts_sensor, np.float64)
    p = p[np.isfinite(p).all(axis=1)]
    r = np.hypot(p[:, 0], p[:, 1])
    lo, hi = float(r.min()), float(r.max())
    crop = ", ".join(f"--{k.replace('_', '-')} {getattr(settings, k)}" for k in ("min_range", "max_range", "max_height")
                     if getattr(settings, k) is not None)
    msg = (f"{path}: no point left to optimise after cropping ({crop}) and ground removal; its {len(p)} finite "
           f"points lie {lo:.1f} to {hi:.1f} m from the sensor origin (horizontally)")
    if settings.max_range is not None and lo > settings.max_range:
        return msg + (". Likely a wrong frame: ranges are measured from each scan's sensor origin, and points in a "
                      "world/map frame need their sensor pose ('pose' in the file, --points-frame world" +
                      ("; --no-ego-motion measures from the world origin" if pose_mode == "identity" else "") +
                      "), or check --poses/--calib; else widen --max-range")
    return msg + ". Likely a wrong crop: check --min-range/--max-range/--max-height and the ground settings"


def finite_mask(rows) -> np.ndarray:
    """(N,) bool: the rows with finite coordinates (the keep op with nothing to crop)."""
    from floxels_ext.ops.lidar import lidar_keep_mask

    return lidar_keep_mask(rows, min_range=None, max_range=None, max_height=None, remove_ground=False,
                           ground_cell=1.0, window_cells=1, ground_threshold=0.0, ground_max_rise=None,
                           grid_distance=1.0, max_cells=1).numpy()


# float32 coordinates beyond this (m) resolve worse than 7.8 mm: such a file is warned about
FLOAT32_FAR = 65536.0


def float32_far_message(path, pts: np.ndarray) -> str | None:
    """A warning for a float32 file whose coordinates lie so far out that float32 has lost
    their precision (judged on <= 4096 rows), else None."""
    sample = np.abs(pts[::max(1, len(pts) // 4096)])
    reach = float(np.max(sample, initial=0.0, where=np.isfinite(sample)))
    if reach <= FLOAT32_FAR:
        return None
    return (f"{path} stores float32 coordinates up to {reach:.4g} m from the origin, where float32 resolves only "
            f"{float(np.spacing(np.float32(reach))):.3g} m: its points lost that precision when the file was "
            f"written; store them as float64 (floxels run reads float64 files in float64), or relative to a "
            f"nearby point")


def beyond_ground_grid(path, pts_sensor: np.ndarray, settings, pose_mode: str) -> str | None:
    """Why no ground was removed from a frame whose points all lie beyond the ground grid's
    reach from its sensor origin (points of a world frame at map scale read with
    ``--no-ego-motion``: the grid is measured from the world origin), else None."""
    p = np.asarray(pts_sensor, np.float64)
    p = p[np.isfinite(p).all(axis=1)]
    if not len(p):
        return None
    r = float(np.hypot(p[:, 0], p[:, 1]).min())
    if r <= settings.grid_distance:
        return None
    return (f"{path}: no ground removed: its points lie {r:.4g} m and more from the sensor origin, beyond the ground "
            f"grid's reach ({settings.grid_distance:g} m)" +
            ("; --no-ego-motion measures from the world origin: give the sensor poses ('pose' in the file with "
             "--points-frame world, or --poses) or --no-ground-removal" if pose_mode == "identity" else
             "; check the poses (--poses/--calib) or the frame of the points"))


def frame_failure(method, options: dict, loader, i: int, n: int, fields=None) -> str | None:
    """Why frame ``i`` (of ``n``; its own scan read) gets no output, or None to write it.
    ``loader.get(j)`` is None for a frame that could not be used (``loader.errors[j]`` says why)."""
    if fields and fields.get("failure"):
        return str(fields["failure"])
    if method.support_frames is None:
        return None
    support = method.support_frames(i, n, options)
    if not support or any(loader.get(j) is not None for j in support):
        return None
    names = [loader.seq.frames[j].path.name for j in support]
    first = loader.errors.get(support[0], "unreadable")
    return (f"no support scan: none of the scans its estimate reads besides its own ({', '.join(names)}) could be "
            f"used, so no flow could be estimated ({first})")
