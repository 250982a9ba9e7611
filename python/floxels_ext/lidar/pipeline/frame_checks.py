"""The checks ``floxels run`` makes on each frame it prepares (``frame_loader.load_frame``): the
rows with finite coordinates, why a frame has no point left after cropping (with the likely
mistake), and a few points so far from the rest of a scan that its distance transforms blow up."""

from __future__ import annotations

import numpy as np

__all__ = ["finite_mask", "empty_crop_message", "far_outliers", "STRAY_DT_BYTES", "STRAY_SPAN"]

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
