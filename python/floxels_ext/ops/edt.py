"""Exact Euclidean distance transforms: fake registration and public wrappers."""

from __future__ import annotations

from collections.abc import Sequence

import torch

from floxels_ext.ops._checks import as_origin, as_points, as_spacing
from floxels_ext.ops._lib import ops_ns
from floxels_ext.ops.grid import DEFAULT_MAX_CELLS, grid_for_points


@torch.library.register_fake("floxels::edt")
def _edt_fake(occupancy, spacing):
    return occupancy.new_empty(occupancy.shape, dtype=torch.float32)


@torch.library.register_fake("floxels::points_to_occupancy")
def _occ_fake(points, origin, spacing, grid_shape):
    return points.new_empty(tuple(grid_shape), dtype=torch.bool)


def edt(occupancy: torch.Tensor, spacing: float = 1.0) -> torch.Tensor:
    """Exact Euclidean distance from every sample of ``occupancy`` (Z, Y, X, bool) to the nearest
    True sample, times ``spacing``, as float32. Equals
    ``scipy.ndimage.distance_transform_edt(~occupancy, sampling=spacing)`` to float32 rounding.
    With no True sample every distance is +inf.
    """
    if not isinstance(occupancy, torch.Tensor) or occupancy.dim() != 3:
        raise ValueError(f"occupancy must be a (Z, Y, X) tensor, got shape {tuple(getattr(occupancy, 'shape', ()))}")
    if occupancy.dtype != torch.bool:
        raise TypeError(f"occupancy must be bool, got {occupancy.dtype}")
    return ops_ns.edt(occupancy.contiguous(), as_spacing(spacing))


def points_to_occupancy(points: torch.Tensor, origin: Sequence[float], spacing: float,
                        grid_shape: Sequence[int]) -> torch.Tensor:
    """Bool (Z, Y, X) grid marking, for each point, its nearest sample
    (index = floor((p - origin)/spacing + 0.5), round half up); points outside are ignored.
    NaN/inf points raise ``ValueError`` here; the raw op ignores them like outside points."""
    points = as_points(points)
    shape = [int(s) for s in grid_shape]
    if len(shape) != 3 or min(shape) < 1:
        raise ValueError(f"grid_shape must be (Z, Y, X) with positive entries, got {grid_shape}")
    return ops_ns.points_to_occupancy(points, as_origin(origin), as_spacing(spacing), shape)


def distance_transform(points: torch.Tensor, spacing: float = 0.1, padding: float = 0.0,
                       origin: Sequence[float] | None = None, grid_shape: Sequence[int] | None = None,
                       max_cells: int = DEFAULT_MAX_CELLS) -> tuple[torch.Tensor, list[float]]:
    """Distance transform (metres, float32 (Z, Y, X)) of a point cloud and the lattice origin.

    Without ``origin``/``grid_shape`` the lattice covers the points plus ``padding`` metres
    (see :func:`grid_for_points`, which enforces ``max_cells``).
    """
    points = as_points(points)
    if origin is None or grid_shape is None:
        origin, grid_shape = grid_for_points(points, spacing, padding, max_cells)
    occ = points_to_occupancy(points, origin, spacing, grid_shape)
    return ops_ns.edt(occ, as_spacing(spacing)), list(origin)
