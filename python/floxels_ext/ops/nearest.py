"""Exact brute-force nearest neighbours (NSFP's Chamfer loss): fake registration and wrapper."""

from __future__ import annotations

import torch

from floxels_ext.ops._checks import as_points
from floxels_ext.ops._lib import ops_ns


@torch.library.register_fake("floxels::nearest_neighbor")
def _fake(x, y):
    return x.new_empty((x.shape[0],), dtype=torch.int64)


def nearest_neighbor(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Index (N,) int64 into ``y`` (M, 3) of the nearest row of each row of ``x`` (N, 3).

    Squared Euclidean distances computed from coordinate differences (exact ordering, no
    ``|x|^2 + |y|^2 - 2 x.y`` cancellation), NaN distances count as +inf, ties keep the lowest
    index (like ``argmin``). ``y`` must be non-empty. Not differentiable (gather the neighbours
    and recompute the distances for gradients). The CUDA kernel splits ``y`` across blocks and
    needs no host synchronisation.
    """
    x, y = as_points(x, "x"), as_points(y, "y")
    if y.shape[0] == 0:
        raise ValueError("nearest_neighbor: the reference cloud y is empty")
    if x.device != y.device:
        raise ValueError(f"x is on {x.device} but y on {y.device}")
    return ops_ns.nearest_neighbor(x, y.to(x.dtype))
