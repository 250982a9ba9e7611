"""Step 3 of the ground removal (:mod:`floxels_ext.lidar.preprocess.masks`): the occlusion guard,
a trimmed least-squares plane under the opened surface that caps it. Shared by the numpy and
the torch paths (the fit runs in numpy on the small grid, so both give identical surfaces).
"""

from __future__ import annotations

import numpy as np

__all__ = ["_plane_cap"]


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
