"""What the estimator returns for one frame."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from floxels_ext.ops.corners import CompactCorners

__all__ = ["FloxelsResult", "DivergedWarning"]


class DivergedWarning(UserWarning):
    """An optimisation diverged: its flow is the start's (zero), not an estimate."""


@dataclass
class FloxelsResult:
    """Everything one optimisation produced."""

    flow: object                       # (N_target, 3): numpy float32 or tensor, like the input
    flow_tensor: torch.Tensor          # (N_kept, 3) float32 on the compute device (finite target rows)
    labels: torch.Tensor | None        # DBSCAN labels of the kept target rows (-1 = noise)
    losses: list[float] = field(default_factory=list)  # total loss per iteration
    best_iter: int = -1                # iteration whose flow is returned
    num_iters: int = 0
    timings: dict[str, float] = field(default_factory=dict)  # seconds per stage
    grid_origin: list[float] | None = None
    voxel_size: float = 0.5
    _corners: CompactCorners | None = None
    _params: torch.Tensor | None = None
    # motion evidence (FloxelsConfig.evidence "score" or "zero"; None when "off"), per target
    # row like ``flow``: ``evidence`` float (metres of distance-transform residual the flow of
    # the point's group removes compared with zero flow; NaN on dropped rows), ``explained``
    # bool (the group passes the test; with "zero" the others' flow is 0). estimator/evidence.py.
    # ``grid`` keeps the optimiser's flow (not zeroed).
    evidence: object | None = None
    explained: object | None = None

    @property
    def diverged(self) -> str | None:
        """Why this optimisation diverged, or None. Diverged: the lowest loss is the start's
        (zero flow; never improved on) while the loss rose far above it (10x, and by more than
        1), what a learning rate far too large does (``lr=1e9`` returned all-zero flow without a
        word; at the default 0.05 the loss rises by ~20 % in the first step at most)."""
        if self.best_iter != 0 or len(self.losses) < 2:
            return None
        start, top = float(self.losses[0]), max(float(v) for v in self.losses[1:])
        if top == top and top <= max(10.0 * start, start + 1.0):  # (NaN: diverged too)
            return None
        return (f"its loss rose from {start:.4g} to {top:.4g} and never went below the start, so its flow is "
                f"the start's (zero), not an estimate")

    @property
    def grid(self) -> torch.Tensor | None:
        """Dense (3, Z, Y, X) flow grid (vertex (iz,iy,ix) at grid_origin + (ix,iy,iz)*voxel_size);
        vertices no point touches hold 0."""
        if self._corners is None:
            return None
        return self._corners.to_dense(self._params)
