"""Re-centring scans far from the origin before any float32 work.

The estimator computes in float32 (the kernels, the solver, the distance transforms). A
map frame at UTM scale puts points at ~5e6 m, where float32 resolves only 0.5 m: the same
scene moved by (4e5, 5e6, 0) lost most of its accuracy (dynamic EPE 0.066 -> 0.23 m).
So every call first subtracts one shift from all its scans **in float64** (a float32 scan
is first widened: the subtraction is exact, but a float32 scan far out has already lost its
resolution, which is warned about), works near the origin, and returns the flow unchanged
(flow is a difference of positions; the grid origins it reports get the shift back).

The shift is a multiple of ``RECENTRE_GRID`` near the window's first non-empty scan: the
voxel (0.5 m) and distance-transform (0.1 m) grids are aligned to the coordinates, and a
shift by a multiple of their cells keeps that alignment (60 m is a multiple of every cell
size of 0.1, 0.2, 0.25, 0.3, 0.4, 0.5, 0.6, 0.75, 0.8, 1, 1.2, 1.5, 2, 2.5, 3, 4, 5 or 6 m),
so the result equals the one near the origin up to float32 rounding. Scans within
``RECENTRE_ABOVE`` of the origin are not touched (float32 resolves 0.06 mm there).
"""

from __future__ import annotations

import numpy as np
import torch

from floxels_ext.ops._small import device_values

__all__ = ["RECENTRE_GRID", "RECENTRE_ABOVE", "FLOAT32_WARN_RESOLUTION", "Recentring"]

RECENTRE_GRID = 60.0
RECENTRE_ABOVE = 1000.0
#: float32 input whose largest coordinate has a float32 spacing above this (m) is warned about
#: (from 65,536 m on: 7.8 mm); float64 input is exact whatever its coordinates.
FLOAT32_WARN_RESOLUTION = 0.005
SAMPLE_ROWS = 4096


def _finite_bounds(t: torch.Tensor) -> tuple[np.ndarray, np.ndarray] | None:
    """(min xyz, max xyz) in float64 of the finite rows of a sample of ``t`` (at most
    ``SAMPLE_ROWS`` rows: enough to place the shift, and cheap on every call), or None.

    A host tensor is reduced by numpy: torch's axis-0 min/max of the strided sample woke the
    intra-op thread pool and cost ~12 ms a frame on a 64-core device host (bench_speed's whole
    frame 14.5 -> 30.8 ms, bench/RESULTS.md "The hidden 13 ms"); numpy takes microseconds.
    A device tensor is reduced where it is (one synchronisation per call)."""
    if t.shape[0] == 0:
        return None
    t = t.detach()[::max(1, t.shape[0] // SAMPLE_ROWS)]
    if t.device.type == "cpu":
        # a numpy view (no ATen op at all); float16/bfloat16, which numpy lacks or reduces
        # slowly, as a float64 copy of the sample
        a = t.numpy() if t.dtype in (torch.float32, torch.float64) else t.to(torch.float64).numpy()
        # Reduced as (3, k) rows: numpy's axis-0 min/max of an (k, 3) array walks it with a
        # stride of 3 and took ~0.13 ms each for 4,096 rows, the transposed copy ~0.01 ms
        # (the whole re-centring 0.42 -> ~0.03 ms of every frame's host time). NaN spreads
        # through min and max and an inf shows in them, so finite bounds say every value of
        # the sample is finite: the row filter runs only when they are not (the same bounds).
        cols = np.ascontiguousarray(a.T)
        lo, hi = cols.min(axis=1), cols.max(axis=1)
        if np.isfinite(lo).all() and np.isfinite(hi).all():
            return lo.astype(np.float64), hi.astype(np.float64)
        keep = np.isfinite(a).all(axis=1)
        if not keep.all():
            a = a[keep]
            if a.shape[0] == 0:
                return None
        return a.min(axis=0).astype(np.float64), a.max(axis=0).astype(np.float64)
    keep = torch.isfinite(t).all(dim=1)
    if not bool(keep.all()):
        t = t[keep]
        if t.shape[0] == 0:
            return None
    lo = t.min(dim=0).values.double().cpu().numpy()
    hi = t.max(dim=0).values.double().cpu().numpy()
    return lo, hi


class Recentring:
    """The one shift of a call (chosen at the first window it sees, then kept, so windows of a
    sequence share scans and distance transforms in one frame)."""

    def __init__(self) -> None:
        self.shift: np.ndarray | None = None  # float64 (3,), zeros when no shift is needed
        self.warned = False

    def decide(self, tensors: list[torch.Tensor]) -> np.ndarray:
        """The shift, chosen from the first scan of ``tensors`` with a finite point."""
        if self.shift is not None:
            return self.shift
        for t in tensors:
            b = _finite_bounds(t)
            if b is None:
                continue
            lo, hi = b
            mid = 0.5 * (lo + hi)
            far = float(np.abs(mid).max())
            self.shift = (np.round(mid / RECENTRE_GRID) * RECENTRE_GRID if far > RECENTRE_ABOVE
                          else np.zeros(3))
            reach = float(max(np.abs(lo).max(), np.abs(hi).max()))
            if t.dtype == torch.float32 and not self.warned and \
                    float(np.spacing(np.float32(reach))) > FLOAT32_WARN_RESOLUTION:
                from floxels_ext.estimator.user_warnings import warn_user

                self.warned = True
                warn_user(f"float32 scans reach {reach:.4g} m from the origin, where float32 resolves only "
                          f"{float(np.spacing(np.float32(reach))):.3g} m: the points have already lost accuracy. "
                          f"Pass float64 scans (the estimator re-centres them in float64 before any float32 "
                          f"work), or subtract a reference point in float64 before converting to float32")
            return self.shift
        self.shift = np.zeros(3)
        return self.shift

    @property
    def active(self) -> bool:
        return self.shift is not None and bool(np.any(self.shift != 0))

    def apply(self, t: torch.Tensor) -> torch.Tensor:
        """``t`` minus the shift, computed in float64, returned as float32 (NaN/inf rows stay
        non-finite); ``t`` itself when there is no shift. Detached either way: the estimator
        returns no gradient, and a tensor that requires one (``requires_grad=True``) is read
        as data (numpy() refuses it)."""
        t = t.detach()
        if not self.active or t.shape[0] == 0:
            return t
        s = device_values(self.shift.tolist(), torch.float64, t.device)
        return (t.to(torch.float64) - s).to(torch.float32)

    def restore(self, origin: list[float] | None) -> list[float] | None:
        """A grid origin of the re-centred frame in the caller's coordinates."""
        if origin is None or not self.active:
            return origin
        return [float(o) + float(s) for o, s in zip(origin, self.shift)]
