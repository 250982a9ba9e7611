"""Argument checks for the public Python wrappers (the C++ side re-checks dtype/shape/device).

The wrappers refuse NaN/inf points with a ValueError. That check costs a reduction (and a
host sync on CUDA) that the optimiser's hot loop, which calls ``torch.ops.floxels`` directly
on already-validated tensors, must not pay every iteration; the raw ops instead follow the
non-finite contract of docs/ops.md (NaN gather rows, scatters ignore the point,
losses become NaN), tested in tests/ops/test_ops_nonfinite.py.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch


def require_tensors(**named) -> None:
    """TypeError naming the first argument that is not a torch.Tensor."""
    for name, t in named.items():
        if not isinstance(t, torch.Tensor):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(t).__name__}")


def check_point_rows(points: torch.Tensor, name: str = "points") -> torch.Tensor:
    """``points`` if it is an (N, 3) float32/float64 tensor (any values, any strides), else the
    TypeError/ValueError naming what is wrong."""
    if not isinstance(points, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(points).__name__}")
    if points.dim() != 2 or points.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {tuple(points.shape)}")
    if points.dtype not in (torch.float32, torch.float64):
        raise TypeError(f"{name} must be float32 or float64, got {points.dtype}")
    return points


def as_points(points: torch.Tensor, name: str = "points") -> torch.Tensor:
    """Points for the optimiser's ops: (N, 3) float32/float64, finite, contiguous."""
    check_point_rows(points, name)
    if points.numel() and not bool(torch.isfinite(points).all()):
        bad = int((~torch.isfinite(points)).any(dim=1).sum())
        raise ValueError(f"{name} contains {bad} row(s) with NaN or inf coordinates")
    return points.contiguous()


def as_origin(origin: Sequence[float], name: str = "origin") -> list[float]:
    try:
        vals = [float(v) for v in (origin.tolist() if isinstance(origin, torch.Tensor) else origin)]
    except (TypeError, ValueError) as exc:
        raise TypeError(f"{name} must be 3 numbers [x0, y0, z0], got {origin!r}") from exc
    if len(vals) != 3:
        raise ValueError(f"{name} must have 3 values [x0, y0, z0], got {len(vals)}")
    if not all(abs(v) < float("inf") for v in vals):
        raise ValueError(f"{name} must be finite, got {vals}")
    return vals


def as_spacing(spacing: float, name: str = "spacing") -> float:
    try:
        s = float(spacing)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"{name} must be a number, got {spacing!r}") from exc
    if not (1e-30 <= s <= 1e30):  # the ops' bounds (csrc/common/check.h check_spacing)
        raise ValueError(f"{name} must be positive and finite (1e-30 <= {name} <= 1e30), got {spacing}")
    return s


def same_device(*named: tuple[str, torch.Tensor]) -> None:
    devs = {t.device for _, t in named}
    if len(devs) > 1:
        desc = ", ".join(f"{n} on {t.device}" for n, t in named)
        raise ValueError(f"floxels: tensors must be on one device, got {desc}")
