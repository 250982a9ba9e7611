"""Choosing a lattice (origin, shape) that covers a point cloud, under a memory cap."""

from __future__ import annotations

import math

import torch

from floxels_ext.ops._checks import as_points, as_spacing

#: Default cap on the number of samples of one grid (float32: 4 bytes each -> 2 GiB).
DEFAULT_MAX_CELLS = 512 * 1024 * 1024


class GridTooLargeError(ValueError):
    """The requested lattice would exceed the memory cap."""


def grid_for_points(points: torch.Tensor, spacing: float, padding: float = 0.0,
                    max_cells: int = DEFAULT_MAX_CELLS) -> tuple[list[float], list[int]]:
    """Smallest lattice with sample spacing ``spacing`` covering ``points`` plus ``padding`` metres.

    Returns ``(origin [x0, y0, z0], shape [Z, Y, X])``. The origin is snapped to a multiple
    of ``spacing`` so grids built for different scans of one sequence share sample positions.
    Raises :class:`GridTooLargeError` (naming the extent) when the lattice would have more
    than ``max_cells`` samples, instead of attempting a huge allocation.
    """
    points = as_points(points)
    spacing = as_spacing(spacing)
    if points.shape[0] == 0:
        raise ValueError("cannot build a grid around an empty point cloud")
    lo = points.min(dim=0).values.double().tolist()
    hi = points.max(dim=0).values.double().tolist()
    return grid_from_bounds(lo, hi, spacing, padding, max_cells)


def point_bounds(clouds: list[torch.Tensor]) -> list[tuple[list[float], list[float]]]:
    """(min xyz, max xyz) of each non-empty cloud, read back in one host synchronisation."""
    if not clouds:
        return []
    mm = torch.stack([torch.cat([c.min(dim=0).values, c.max(dim=0).values]).double() for c in clouds]).tolist()
    return [(r[:3], r[3:]) for r in mm]


def grid_from_bounds(lo: list[float], hi: list[float], spacing: float, padding: float = 0.0,
                     max_cells: int = DEFAULT_MAX_CELLS) -> tuple[list[float], list[int]]:
    """:func:`grid_for_points` from the points' bounds (``lo``/``hi`` = min/max xyz)."""
    lo = [v - padding for v in lo]
    hi = [v + padding for v in hi]
    origin = [math.floor(v / spacing) * spacing for v in lo]
    n_xyz = [int(math.floor((h - o) / spacing + 1e-9)) + 2 for h, o in zip(hi, origin)]
    cells = n_xyz[0] * n_xyz[1] * n_xyz[2]
    if cells > max_cells:
        ext = ", ".join(f"{h - l:.1f}" for l, h in zip(lo, hi))
        raise GridTooLargeError(
            f"a grid at {spacing} m over an extent of ({ext}) m would have {cells:,} samples "
            f"(cap {max_cells:,}); crop the points, or raise the cap: FloxelsConfig.max_dt_cells "
            f"(the ops' max_cells=)")
    return origin, [n_xyz[2], n_xyz[1], n_xyz[0]]
