"""Scan preprocessing for real lidar: rigid transforms (ego-motion compensation), range/height
cropping as in the paper's protocol, and ground removal.

Ground removal (:func:`ground_mask`) is a single-window *progressive morphological filter*
(Zhang et al., "A progressive morphological filter for removing nonground measurements from
airborne LIDAR data", IEEE TGRS 2003), applied to a bird's-eye-view grid:

0. outliers far below the ground (multipath) or far above the sensor are found against a robust
   reference height (:mod:`floxels_ext.lidar.ground_outliers`: block quartiles, a cone around
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

from dataclasses import dataclass

import numpy as np

__all__ = ["transform_points", "host_rows", "relative_pose", "ground_estimate", "ground_surface", "ground_mask",
           "crop_mask", "Preprocess", "preprocess_mask", "preprocess_mask_numpy", "preprocess_classes",
           "preprocess_classes_numpy", "CROPPED", "KEPT", "GROUND", "OUTLIER"]

# Per-point classes of :func:`preprocess_classes` (uint8): dropped by the range/height crop or
# non-finite, kept (optimised), removed as ground, removed as an outlier (step 0 below).
CROPPED, KEPT, GROUND, OUTLIER = 0, 1, 2, 3


def transform_points(points: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Apply a 4x4 rigid transform to (N, 3) points (NaN rows stay NaN), in float64; float32 out.
    (The compiled :func:`floxels_ext.ops.rigid_transform`: numpy's ``p @ R.T + t`` to the last
    bit of the float32 result, without the GIL.)"""
    import torch

    from floxels_ext.ops.lidar import rigid_transform

    out = rigid_transform(host_rows(np.asarray(points).reshape(-1, 3)), torch.from_numpy(np.asarray(T, np.float64)))
    return out.numpy().astype(np.float32, copy=False)


def host_rows(points: np.ndarray):
    """``points`` as a CPU tensor for the lidar ops, without a copy where torch can view it
    (float32/float64, positive strides, writeable; the ops read any strides); other dtypes
    become float64."""
    import torch

    p = np.asarray(points)
    if p.dtype not in (np.float32, np.float64):
        p = p.astype(np.float64)
    if not p.flags.writeable or any(s <= 0 or s % p.itemsize for s in p.strides):
        p = np.ascontiguousarray(p)
        if not p.flags.writeable:
            p = p.copy()
    return torch.from_numpy(p)


def relative_pose(pose_from: np.ndarray, pose_to: np.ndarray) -> np.ndarray:
    """Transform taking coordinates of the frame with sensor-to-world pose ``pose_from`` into
    the frame with pose ``pose_to``: ``inv(pose_to) @ pose_from``."""
    return np.linalg.solve(np.asarray(pose_to, np.float64), np.asarray(pose_from, np.float64))


def _trimmed_plane(xy: np.ndarray, z: np.ndarray, iters: int = 6, keep_above: float = 0.2):
    """z = a x + b y + c fitted to the cells, dropping those well above the fit (objects)."""
    sel = np.ones(len(z), bool)
    coef = None
    A = np.c_[xy, np.ones(len(z))]
    for _ in range(iters):
        if sel.sum() < 10:
            break
        coef = np.linalg.lstsq(A[sel], z[sel], rcond=None)[0]
        new = (z - A @ coef) <= keep_above
        if np.array_equal(new, sel):
            break
        sel = new
    return coef


def _plane_cap(opened: np.ndarray, cell_size: float, max_rise: float | None) -> np.ndarray:
    """Step 3 of the module docstring: cap the opened surface at the trimmed plane + max_rise.
    Shared by the numpy and the torch implementations (the least-squares fit runs here, in
    numpy, on the small grid, so both give identical surfaces)."""
    if max_rise is None:
        return opened
    cells = np.argwhere(np.isfinite(opened))
    coef = _trimmed_plane((cells + 0.5) * cell_size, opened[cells[:, 0], cells[:, 1]])
    if coef is None:
        return opened
    shape = opened.shape
    ci = np.indices(shape).reshape(2, -1).T
    plane = (np.c_[(ci + 0.5) * cell_size, np.ones(len(ci))] @ coef).reshape(shape)
    return np.minimum(opened, plane + max_rise)


def _check_ground_args(cell_size, window, max_distance) -> None:
    if not (cell_size > 0 and window > 0):
        raise ValueError(f"cell_size and window must be > 0, got {cell_size}, {window}")
    if max_distance is not None and not (np.isfinite(max_distance) and max_distance > 0):
        raise ValueError(f"max_distance must be a finite number > 0 (or None), got {max_distance}")
    if max_distance is not None and (2 * max_distance / cell_size + 1) ** 2 > MAX_GROUND_CELLS:
        raise ValueError(f"a ground grid of {cell_size} m cells over +-{max_distance} m would have more than "
                         f"{MAX_GROUND_CELLS:,} cells; lower max_distance or raise cell_size")


# The ground grid covers at most this many cells (+-500 m at 0.5 m): the grid, not the points'
# extent, bounds the memory, so a stray point kilometres away costs nothing.
MAX_GROUND_CELLS = 2001 * 2001


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

    from floxels_ext.lidar.ground_outliers import ground_reference, outlier_flags

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


def _window_cells(window: float, cell_size: float) -> int:
    return max(1, int(round(window / cell_size)) | 1)  # odd, so the window is centred


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


@dataclass(frozen=True)
class Preprocess:
    """Per-scan preprocessing settings (the paper's protocol by default)."""

    min_range: float | None = 3.0       # m, horizontal distance to the sensor
    max_range: float | None = 50.0
    max_height: float | None = 4.0      # m above the local ground surface
    remove_ground: bool = True
    ground_cell: float = 0.5            # m, grid cell of the lowest-point map
    ground_window: float = 8.0          # m, opening window (wider than the largest object)
    ground_threshold: float = 0.3       # m above the ground surface still counted as ground
    ground_max_rise: float | None = 0.5  # m the surface may rise above the fitted plane (None: no cap)
    # m: without max_range, only points this close (horizontally) build the ground grid; farther
    # ones have no ground height (never ground; dropped by the max_height crop)
    ground_max_distance: float = 200.0
    # m under the robust reference height (ground_outliers.py) below which a point is an outlier
    # (multipath), and m above the sensor above which it is one; None: no such test
    outlier_below: float | None = 1.0
    outlier_above: float | None = 20.0

    def __post_init__(self) -> None:
        for name in ("min_range", "max_range", "max_height", "outlier_below", "outlier_above"):
            v = getattr(self, name)
            if v is not None and not (np.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be a finite number >= 0 (or None), got {v}")
        if self.min_range is not None and self.max_range is not None and self.min_range >= self.max_range:
            raise ValueError(f"min_range ({self.min_range}) must be below max_range ({self.max_range})")
        for name in ("ground_cell", "ground_window", "ground_threshold", "ground_max_distance"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {v}")
        _check_ground_args(self.ground_cell, self.ground_window, self.grid_distance)

    @property
    def grid_distance(self) -> float:
        """Horizontal distance (m) of the points that build the ground grid: the range crop plus
        one window (so the opening near the crop edge sees the same neighbourhood), the crop
        first, so far-away points cannot blow the grid up."""
        if self.max_range is None:
            return self.ground_max_distance
        return self.max_range + self.ground_window


def preprocess_mask(points_sensor: np.ndarray, settings: Preprocess = Preprocess(), device=None) -> np.ndarray:
    """(N,) bool of the points of one scan (in its sensor frame, z up) kept by ``settings``.

    ``device`` None or "cpu": the compiled CPU op (:func:`floxels_ext.ops.lidar_keep_mask`, a few
    ms a 200k-point scan, without the GIL); a CUDA device: the grid work there
    (:func:`floxels_ext.lidar.preprocess_torch.preprocess_mask_torch`). Both give the masks of
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
        from floxels_ext.lidar.preprocess_torch import preprocess_classes_torch

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
