"""Exact DBSCAN with scikit-learn's labels: fake registration and the public wrapper."""

from __future__ import annotations

import math

import torch

from floxels_ext.ops._checks import as_points
from floxels_ext.ops._lib import ops_ns


@torch.library.register_fake("floxels::dbscan")
def _fake(points, eps, min_samples):
    # Label VALUES depend on the data, but the shape is always (N,).
    return points.new_empty((points.shape[0],), dtype=torch.int64)


def dbscan(points: torch.Tensor, eps: float = 0.5, min_samples: int = 4) -> torch.Tensor:
    """DBSCAN labels (N,) int64 of ``points`` (N, 3), -1 for noise.

    Identical to ``sklearn.cluster.DBSCAN(eps=eps, min_samples=min_samples).fit(points).labels_``
    (Euclidean metric): a point's neighbourhood is every point (itself included) with
    distance <= eps, computed in float64; clusters are numbered in order of their smallest
    core-point index and a border point joins the smallest-numbered neighbouring cluster.
    Not differentiable. The labels are returned on the device of ``points``; CUDA input is
    clustered by the GPU kernel (same labels as the CPU kernel, bit for bit; it synchronises
    the current stream once). Setting ``FLOXELS_CPU_DBSCAN=1`` before the first call routes
    CUDA input to the CPU kernel instead (escape hatch). NaN/inf points raise (``ValueError``
    here, ``RuntimeError`` from the raw op).
    """
    points = as_points(points)
    eps = float(eps)
    if not (eps > 0 and math.isfinite(eps)):
        raise ValueError(f"eps must be positive and finite, got {eps}")
    if isinstance(min_samples, bool) or int(min_samples) != min_samples or int(min_samples) < 1:
        raise ValueError(f"min_samples must be an integer >= 1, got {min_samples}")
    return ops_ns.dbscan(points, eps, int(min_samples))
