"""Validation and normalisation of the scans handed to the estimators.

Policy for bad input (documented in the README):
* fewer than 2 scans, a target index out of range, scans of different dtypes or kinds
  (numpy vs tensor), or arrays that are not (N, 3) floats: ``ValueError``/``TypeError``;
* rows with NaN/inf coordinates are dropped with a ``UserWarning``; in the target scan
  their flow is returned as NaN so the output keeps one row per input point;
* an empty target scan gives an empty (0, 3) flow; an empty support scan contributes no loss.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch


@dataclass
class PreparedScans:
    points: list[torch.Tensor]     # finite rows only, float32, on the compute device
    finite_masks: list[torch.Tensor]  # (N_i,) bool on the compute device: which input rows were kept
    target: int
    offsets: list[int]             # time offset of every support scan (index - target)
    supports: list[int]            # indices of the support scans
    was_numpy: bool
    in_dtype: torch.dtype | np.dtype
    in_device: torch.device
    num_target_points: int


def _as_tensor(scan, i: int) -> torch.Tensor:
    if isinstance(scan, np.ndarray):
        t = torch.from_numpy(np.ascontiguousarray(scan))
    elif isinstance(scan, torch.Tensor):
        t = scan
    else:
        raise TypeError(f"scan {i} must be a numpy array or torch tensor, got {type(scan).__name__}")
    if t.dim() != 2 or t.shape[1] != 3:
        raise ValueError(f"scan {i} must have shape (N, 3), got {tuple(t.shape)}")
    if not t.dtype.is_floating_point:
        raise TypeError(f"scan {i} must hold floats (float32/float64), got {t.dtype}")
    return t


def resolve_device(device, first: torch.Tensor | np.ndarray) -> torch.device:
    if device is not None:
        dev = torch.device(device)
    elif isinstance(first, torch.Tensor):
        dev = first.device
    else:
        dev = torch.device("cpu")
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError("device='cuda' requested but no CUDA device is available")
    if dev.type not in ("cpu", "cuda"):
        raise ValueError(f"unsupported device {dev}; use 'cpu' or 'cuda'")
    return dev


def prepare_scans(scans: Sequence, target: int | None, device, converted: dict | None = None,
                  first_index: int = 0) -> PreparedScans:
    """Validate a window of scans and move them to the compute device.

    ``converted`` (sequence index -> (points, finite mask)) lets sliding windows over one
    sequence convert, copy and NaN-check each scan once; ``first_index`` is the sequence
    index of ``scans[0]`` (also used in warnings)."""
    if isinstance(scans, (np.ndarray, torch.Tensor)):
        raise TypeError("scans must be a sequence of (N_i, 3) arrays, not a single array")
    scans = list(scans)
    if len(scans) < 2:
        raise ValueError(f"Floxels needs at least 2 scans (a target and a support scan), got {len(scans)}")
    if len(scans) > 13:
        raise ValueError(f"at most 13 scans are supported per window, got {len(scans)}")
    kinds = {isinstance(s, np.ndarray) for s in scans}
    if len(kinds) > 1:
        raise TypeError("scans mix numpy arrays and torch tensors; pass one kind")
    tensors = [_as_tensor(s, i) for i, s in enumerate(scans)]
    dtypes = {t.dtype for t in tensors}
    if len(dtypes) > 1:
        raise TypeError(f"scans have different dtypes {sorted(str(d) for d in dtypes)}; convert them to one dtype")
    devices = {t.device for t in tensors}
    if len(devices) > 1:
        raise ValueError(f"scans are on different devices {sorted(str(d) for d in devices)}")
    n = len(tensors)
    if target is None:
        target = n // 2
    if not isinstance(target, (int, np.integer)) or isinstance(target, bool):
        raise TypeError(f"target must be an integer index, got {type(target).__name__}")
    target = int(target)
    if target < 0:
        target += n
    if not 0 <= target < n:
        raise IndexError(f"target index {target} is out of range for {n} scans")
    dev = resolve_device(device, scans[0])

    points, masks = [], []
    for i, t in enumerate(tensors):
        key = first_index + i
        if converted is not None and key in converted:
            t, finite = converted[key]
        else:
            t, finite = _finite_rows(t, dev, key, i == target)
            if converted is not None:
                converted[key] = (t, finite)
        points.append(t)
        masks.append(finite)
    supports = [i for i in range(n) if i != target]
    return PreparedScans(points=points, finite_masks=masks, target=target,
                         offsets=[i - target for i in supports], supports=supports,
                         was_numpy=isinstance(scans[0], np.ndarray), in_dtype=scans[0].dtype,
                         in_device=tensors[0].device, num_target_points=tensors[target].shape[0])


def _finite_rows(t: torch.Tensor, dev: torch.device, index: int, is_target: bool):
    """float32 contiguous copy on ``dev`` without the NaN/inf rows (warned about), and the mask."""
    t = t.to(device=dev, dtype=torch.float32)
    finite = torch.isfinite(t).all(dim=1)
    bad = int((~finite).sum())
    if bad:
        warnings.warn(f"scan {index}: dropping {bad} point(s) with NaN/inf coordinates"
                      + (" (their flow is NaN)" if is_target else ""), UserWarning, stacklevel=4)
        t = t[finite]
    return t.contiguous(), finite


def restore_output(flow_kept: torch.Tensor, prep: PreparedScans):
    """Scatter the flow of the kept target rows back to all input rows (NaN for dropped ones)
    and convert to what the caller passed in: numpy float32, or a tensor of the input's
    dtype on the input's device."""
    mask = prep.finite_masks[prep.target]
    if flow_kept.shape[0] == prep.num_target_points:
        full = flow_kept
    else:
        full = torch.full((prep.num_target_points, 3), float("nan"), dtype=flow_kept.dtype,
                          device=flow_kept.device)
        full[mask] = flow_kept
    if prep.was_numpy:
        return full.detach().cpu().numpy().astype(np.float32, copy=False)
    return full.detach().to(device=prep.in_device, dtype=prep.in_dtype)

