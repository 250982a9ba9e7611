"""Two more looks at the groups the evidence test passed (``FloxelsConfig.evidence_upright``,
``FloxelsConfig.evidence_far``; issue 47's "without raising static EPE").

The evidence test (estimator/evidence.py) scores a group's flow on the residual the optimiser
minimised, over the same scans: the gain is in-sample, and static structure whose samples move
with the sensor (a 32-beam lidar's rings meet a facade or a barrier at heights and ranges that
change as the sensor moves) passes with flows that track those samples.

``upright`` (:func:`upright_groups`): a group whose final flow (the optimiser's, or its refined
or spread rigid motion) is more vertical than horizontal is not a road user, and keeps none.
Vehicles, cyclists and pedestrians move along the ground (the ground is removed; a 10 % slope
gives a vertical part a tenth of the motion); a ring sliding up or down a facade or a pole as the
sensor approaches it is fitted by a vertical flow. Judged on the final flow (estimator/post.py):
at a sequence's first frame the optimiser left running pedestrians a mostly vertical flow that
the refinement, which also solves without vertical velocity, corrected. On the tuning seeds the
clusters whose mean flow is mostly vertical (|f_z| > |f_xy|) are static structure (4,127 points,
0.00024 of the mean static EPE of 0.0049) and movers whose flow is wrong anyway (222 points, as
far from the truth as zero flow); moving clusters' flows lie within a degree of the horizontal
(median), static ones that keep a flow 15 degrees off it (bench/RESULTS.md, issue 47's static EPE).

``far`` (:func:`far_fails`): with weights 1/t^2 the nearest scans (t = +-1) carry most of the
window's weight, so a flow fitted to those scans' samples alone passes. A group whose points
are free to take their own flow (few points, unclustered: DBSCAN noise, grouped per flow-grid
cell) finds, at 30-50 m from a 32-beam lidar where the rings are 0.5-1 m apart, a place in the
nearest scan that its own surface's samples fit better than its own position. A constant motion
that the nearest scans support is supported by the farther scans as well; a fit to the nearest
scans' sampling is less often. So a group that passed must also remove a share of the farther
scans' zero-flow residual: with the nearest scans' weights set to 0, the farther scans' weighted
mean residuals ``R_flow``, ``R_zero`` over what they saw, and ``R_zero - R_flow > ratio *
R_zero`` (the evidence test's ratio; a ratio of two means over the same seen scans, so a group
the farther scans saw in part is judged alike). A group no farther scan saw (``R_zero`` 0), or
a window without farther scans (a frame pair), keeps its verdict.

Cost: ``upright``: the clusters' mean flow (one integer ``index_add_``) and element-wise ops;
``far``: one more ``floxels::dt_evidence`` call (4 CUDA kernels). No host synchronisation.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from floxels_ext.estimator.evidence import run_evidence
from floxels_ext.estimator.group_sums import cluster_means

__all__ = ["far_fails", "upright_groups", "FAR_MODES"]

# FloxelsConfig.evidence_far: "off", "unclustered" (only DBSCAN noise's cell groups are looked at
# again), "all" (every group)
FAR_MODES = ("off", "unclustered", "all")


def far_fails(points: torch.Tensor, flow: torch.Tensor, labels: torch.Tensor | None, cells: torch.Tensor,
              dts: Sequence[torch.Tensor], origins, offsets: Sequence[float], weights: Sequence[float], *,
              dt_cell: float, truncation: float, ratio: float, observed: torch.Tensor | None,
              unclustered: bool) -> torch.Tensor | None:
    """(n,) bool: the points whose group's flow does not explain the window's farther scans (every
    scan but the nearest in time) better than zero flow by ``ratio`` of their zero-flow residual;
    None where the window has no farther scan. Groups as :func:`~floxels_ext.estimator.evidence.run_evidence`'s
    (runs of ``labels``, for label -1 of ``cells``); ``unclustered``: only label -1's groups can fail."""
    if points.shape[0] == 0 or not dts:
        return None
    near = min(abs(float(t)) for t in offsets)
    far = [float(w) if abs(float(t)) > near * (1 + 1e-6) else 0.0 for t, w in zip(offsets, weights)]
    total = sum(far)
    if total <= 0:
        return None
    # the evidence test's own call with the farther scans' weights (it normalises them); only its
    # residuals are read
    ev = run_evidence(points, flow, labels, cells, dts, origins, offsets, far, dt_cell=dt_cell,
                      truncation=truncation, margin=0.0, ratio=ratio, observed=observed)
    rf, rz = ev.residual_flow, ev.residual_zero
    fails = (rz > 0) & (rz - rf <= ratio * rz)
    if unclustered and labels is not None:
        fails &= labels < 0
    return fails


def upright_groups(flow: torch.Tensor, labels: torch.Tensor | None, num_clusters: int | None) -> torch.Tensor:
    """(n,) bool: the points whose group's flow is more vertical than horizontal (|f_z| > |f_xy|):
    a cluster by its mean flow (:func:`~floxels_ext.estimator.group_sums.cluster_means`, the same
    bits on any device), an unclustered point by its own. A NaN flow is not upright."""
    f = flow
    if labels is not None and num_clusters is None and labels.numel():
        num_clusters = int(labels.max()) + 1  # (a host synchronisation; the estimator passes it)
    if labels is not None and num_clusters:
        mean, _ = cluster_means(flow, labels, int(num_clusters))
        lab = labels.long()
        f = torch.where((lab >= 0)[:, None], mean[lab.clamp_min(0)], flow)
    return f[:, 2].abs() > f[:, :2].norm(dim=1)
