"""Scan preprocessing for real lidar: range/height cropping as in the paper's protocol and ground
removal, per point (masks and classes), with the numpy reference of the compiled op. The settings
and classes are in ``settings``, the rigid transforms (ego-motion compensation) in ``transform``.

Ground removal (:func:`ground_mask`) is a single-window *progressive morphological filter*
(Zhang et al., "A progressive morphological filter for removing nonground measurements from
airborne LIDAR data", IEEE TGRS 2003), applied to a bird's-eye-view grid:

0. outliers far below the ground (multipath) or far above the sensor are found against a robust
   reference height (:mod:`floxels_ext.lidar.preprocess.ground_outliers`: block quartiles, a cone around
   the ground near the sensor); they build no cell, are never kept and are counted;
1. keep the lowest z of every ``cell_size`` cell (a lower envelope of the scene);
2. morphological *opening* of that height map with a square window of ``window`` metres
   (min filter, then max filter; empty cells take no part). Opening removes every bump
   narrower than the window (cars, people, poles, walls, vegetation) and leaves planes and
   slopes unchanged, so the result is the local ground surface;
3. occlusion guard: where objects hide the ground for more than the window (a row of parked
   cars, the shadow behind a truck) the opened surface sits on top of the objects. A plane is
   fitted to the opened surface by trimmed least squares (cells more than 0.2 m above the
   current fit are dropped and the fit repeated), and the surface is capped at that plane plus
   ``max_rise`` metres (``None``: no cap);
4. a point is ground when it lies less than ``height_threshold`` above that surface. The
   default 0.3 m is the threshold of the Argoverse 2 scene-flow protocol's ground map.

It needs no plane assumption (ramps and cambered roads work) and costs two 2-D filters per scan.
Objects wider than ``window`` in both directions (a bus seen from above) could be taken for
ground only where no ground is visible within the window around them, which lidar at street
level rarely produces; raise ``window`` for large vehicles, lower it for steep terrain.
"""

from __future__ import annotations

import numpy as np

from floxels_ext.lidar.preprocess.ground_plane import _plane_cap
from floxels_ext.lidar.preprocess.settings import (CROPPED, GROUND, KEPT, MAX_GROUND_CELLS, OUTLIER, Preprocess,
                                                   _check_ground_args, _window_cells)
from floxels_ext.lidar.preprocess.transform import host_rows

__all__ = ["ground_estimate", "ground_surface", "ground_mask", "crop_mask", "preprocess_mask", "preprocess_mask_numpy",
           "preprocess_classes", "preprocess_classes_numpy"]


def ground_estimate(points: np.ndarray, *, cell_size: float = 0.5, window: float = 8.0,
                    max_rise: float | None = 0.5, max_distance: float | None = 200.0,
                    outlier_below: float | None = 1.0, outlier_above: float | None = 20.0):
    """Local ground height under each point (see the module docstring) and the outliers of
    step 0: ``(surface (N,) float64, outlier (N,) bool)``. The surface is NaN for non-finite
    rows and for points farther than ``max_distance`` metres (horizontally) from the frame
    origin: only the points within that distance build the grid (``None``: all finite points,
    whose extent must then stay within :data:`MAX_GROUND_CELLS` cells); those points only can
    be outliers. ``outlier_below`` / ``outlier_above`` None: no such outliers."""
    from scipy import ndimage

    from floxels_ext.lidar.preprocess.ground_outliers import ground_reference, outlier_flags

    _check_ground_args(cell_size, window, max_distance)
    p = np.asarray(points, np.float64)
    out = np.full(len(p), np.nan)
    outlier = np.zeros(len(p), bool)
    ok = np.isfinite(p).all(axis=1)
    if max_distance is not None:
        with np.errstate(invalid="ignore"):
            ok &= np.hypot(p[:, 0], p[:, 1]) <= max_distance
    if not ok.any():
        return out, outlier
    q = p[ok]
    lo = np.floor(q[:, :2].min(axis=0) / cell_size)
    hi = np.floor(q[:, :2].max(axis=0) / cell_size)
    if np.prod(hi - lo + 1) > MAX_GROUND_CELLS:
        raise ValueError(f"points spread over {(hi - lo + 1)[0] * cell_size:.0f} x {(hi - lo + 1)[1] * cell_size:.0f} m: "
                         f"the ground grid would exceed {MAX_GROUND_CELLS:,} cells; crop them (max_distance)")
    ij = (np.floor(q[:, :2] / cell_size) - lo).astype(np.int64)
    shape = tuple((hi - lo + 1).astype(np.int64))
    size = _window_cells(window, cell_size)
    lowest = np.full(shape, np.inf)
    np.minimum.at(lowest, (ij[:, 0], ij[:, 1]), q[:, 2])
    if outlier_below is not None or outlier_above is not None:
        ref = ground_reference(lowest, lo, cell_size, size) if outlier_below is not None else None
        bad = outlier_flags(q[:, 2], ij, ref, size, outlier_below, outlier_above)
        if bad.any():
            outlier[np.flatnonzero(ok)[bad]] = True
            lowest = np.full(shape, np.inf)  # rebuilt without them
            np.minimum.at(lowest, (ij[~bad, 0], ij[~bad, 1]), q[~bad, 2])
    eroded = ndimage.minimum_filter(lowest, size=size, mode="constant", cval=np.inf)
    # empty cells must not raise the dilation: they become -inf there
    opened = ndimage.maximum_filter(np.where(np.isfinite(eroded), eroded, -np.inf), size=size,
                                    mode="constant", cval=-np.inf)
    opened = _plane_cap(opened, cell_size, max_rise)
    out[ok] = opened[ij[:, 0], ij[:, 1]]
    return out, outlier


def ground_surface(points: np.ndarray, *, cell_size: float = 0.5, window: float = 8.0,
                   max_rise: float | None = 0.5, max_distance: float | None = 200.0,
                   outlier_below: float | None = 1.0, outlier_above: float | None = 20.0):
    """The surface of :func:`ground_estimate` alone: an (N,) float64 array (outliers have the
    surface of their cell)."""
    return ground_estimate(points, cell_size=cell_size, window=window, max_rise=max_rise, max_distance=max_distance,
                           outlier_below=outlier_below, outlier_above=outlier_above)[0]


def ground_mask(points: np.ndarray, *, cell_size: float = 0.5, window: float = 8.0,
                max_rise: float | None = 0.5, height_threshold: float = 0.3,
                surface: np.ndarray | None = None) -> np.ndarray:
    """(N,) bool: points less than ``height_threshold`` metres above the local ground surface.
    ``points`` in a frame whose z axis points up (sensor or ego frame); non-finite rows False."""
    if surface is None:
        surface = ground_surface(points, cell_size=cell_size, window=window, max_rise=max_rise)
    z = np.asarray(points, np.float64)[:, 2]
    with np.errstate(invalid="ignore"):
        return (z - surface) < height_threshold


def crop_mask(points: np.ndarray, *, min_range: float | None = 3.0, max_range: float | None = 50.0,
              max_height: float | None = 4.0, ground_height: np.ndarray | float | None = None) -> np.ndarray:
    """(N,) bool of the finite points inside the paper's protocol box: horizontal distance to the
    frame origin (the sensor) in [min_range, max_range], height above the ground at most
    ``max_height``. Heights are taken above ``ground_height`` (per point, e.g.
    :func:`ground_surface`, or one number); without it, above z = 0. ``None`` disables a limit."""
    p = np.asarray(points, np.float64)
    keep = np.isfinite(p).all(axis=1)
    r = np.hypot(p[:, 0], p[:, 1])
    with np.errstate(invalid="ignore"):
        if min_range is not None:
            keep &= r >= min_range
        if max_range is not None:
            keep &= r <= max_range
        if max_height is not None:
            g = 0.0 if ground_height is None else np.asarray(ground_height, np.float64)
            keep &= (p[:, 2] - g) <= max_height
    return keep & np.isfinite(p).all(axis=1)


def preprocess_mask(points_sensor: np.ndarray, settings: Preprocess = Preprocess(), device=None) -> np.ndarray:
    """(N,) bool of the points of one scan (in its sensor frame, z up) kept by ``settings``.

    ``device`` None or "cpu": the compiled CPU op (:func:`floxels_ext.ops.lidar_keep_mask`, a few
    ms a 200k-point scan, without the GIL); a CUDA device: the grid work there
    (:func:`floxels_ext.lidar.preprocess.masks_torch.preprocess_mask_torch`). Both give the masks of
    :func:`preprocess_mask_numpy`, the reference (tests compare them)."""
    if device is not None and str(device) != "cpu":
        return preprocess_classes(points_sensor, settings, device) == KEPT
    from floxels_ext.ops.lidar import lidar_keep_mask

    return lidar_keep_mask(host_rows(points_sensor), **_op_arguments(settings)).numpy()


def preprocess_classes(points_sensor: np.ndarray, settings: Preprocess = Preprocess(), device=None) -> np.ndarray:
    """(N,) uint8 class of every point of one scan: :data:`CROPPED` (or non-finite), :data:`KEPT`,
    :data:`GROUND`, :data:`OUTLIER`; ``== KEPT`` is :func:`preprocess_mask`. Devices as there;
    reference: :func:`preprocess_classes_numpy`."""
    if device is not None and str(device) != "cpu":
        from floxels_ext.lidar.preprocess.masks_torch import preprocess_classes_torch

        return preprocess_classes_torch(points_sensor, settings, device)
    from floxels_ext.ops.lidar import lidar_point_classes

    return lidar_point_classes(host_rows(points_sensor), **_op_arguments(settings)).numpy()


def _op_arguments(s: Preprocess) -> dict:
    return dict(min_range=s.min_range, max_range=s.max_range, max_height=s.max_height,
                remove_ground=s.remove_ground, ground_cell=s.ground_cell,
                window_cells=_window_cells(s.ground_window, s.ground_cell), ground_threshold=s.ground_threshold,
                ground_max_rise=s.ground_max_rise, grid_distance=s.grid_distance, max_cells=MAX_GROUND_CELLS,
                outlier_below=s.outlier_below, outlier_above=s.outlier_above)


def preprocess_mask_numpy(points_sensor: np.ndarray, settings: Preprocess = Preprocess()) -> np.ndarray:
    """The reference of :func:`preprocess_mask` in numpy/scipy (tens of ms a 200k-point scan)."""
    return preprocess_classes_numpy(points_sensor, settings) == KEPT


def preprocess_classes_numpy(points_sensor: np.ndarray, settings: Preprocess = Preprocess()) -> np.ndarray:
    """The reference of :func:`preprocess_classes`. Precedence: non-finite or outside the range
    crop, then outlier, then above ``max_height``, then ground, else kept."""
    need_surface = settings.remove_ground or settings.max_height is not None
    p = np.asarray(points_sensor, np.float64)
    in_range = crop_mask(p, min_range=settings.min_range, max_range=settings.max_range, max_height=None)
    cls = np.full(len(p), CROPPED, np.uint8)
    if not need_surface:
        cls[crop_mask(p, min_range=settings.min_range, max_range=settings.max_range,
                      max_height=settings.max_height)] = KEPT
        return cls
    surface, outlier = ground_estimate(p, cell_size=settings.ground_cell, window=settings.ground_window,
                                       max_rise=settings.ground_max_rise, max_distance=settings.grid_distance,
                                       outlier_below=settings.outlier_below, outlier_above=settings.outlier_above)
    with np.errstate(invalid="ignore"):
        h = p[:, 2] - surface
        low_enough = (h <= settings.max_height) if settings.max_height is not None else np.ones(len(p), bool)
        ground = (h < settings.ground_threshold) if settings.remove_ground else np.zeros(len(p), bool)
    cls[in_range & low_enough & ~ground] = KEPT
    cls[in_range & low_enough & ground] = GROUND
    cls[in_range & outlier] = OUTLIER
    return cls
