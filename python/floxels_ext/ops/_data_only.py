"""What the data-only ops of the distance-transform family share (``dt_residual``, ``dt_sample``,
``dt_evidence``, ``rigid_lm``, ``velocity_search``): their no-gradient registration and the
checks of their optional per-point ``observed`` bits and per-cluster row ``segments``."""

from __future__ import annotations

import torch

from floxels_ext.ops._checks import require_tensors

__all__ = ["register_data_only", "check_observed", "check_segments"]


def register_data_only(name: str, hint: str = "") -> None:
    """Register ``floxels::<name>``'s autograd: a backward through it raises, naming the op."""

    def backward(ctx, *grads):
        raise RuntimeError(f"floxels::{name} is a data-only op: no gradient flows through it{hint}")

    torch.library.register_autograd(f"floxels::{name}", backward, setup_context=lambda ctx, inputs, output: None)


def check_observed(op: str, observed, points: torch.Tensor):
    """``observed`` checked: None, or an (N,) int32 tensor on the points' device (bit k of row i:
    scan k counts for point i); returned contiguous."""
    if observed is None:
        return None
    require_tensors(observed=observed)
    if observed.dim() != 1 or observed.shape[0] != points.shape[0] or observed.dtype != torch.int32:
        raise ValueError(f"{op}: observed must be an ({points.shape[0]},) int32 tensor (a bit mask per point), "
                         f"got {observed.dtype} {tuple(observed.shape)}")
    if observed.device != points.device:
        raise ValueError(f"{op}: observed is on {observed.device} but points are on {points.device}")
    return observed.contiguous()


def check_segments(op: str, segments, points: torch.Tensor, num_clusters: int | None = None) -> torch.Tensor:
    """``segments`` checked: an int64 (C + 1,) tensor on the points' device (``num_clusters`` = C
    when known) rising from 0 to the number of rows (one host read); returned contiguous."""
    require_tensors(segments=segments)
    want = "(C + 1,)" if num_clusters is None else f"({num_clusters + 1},)"
    if (segments.dim() != 1 or segments.shape[0] < 1 or segments.dtype != torch.int64
            or (num_clusters is not None and segments.shape[0] != num_clusters + 1)):
        raise ValueError(f"{op}: segments must be a {want} int64 tensor of row offsets, got "
                         f"{segments.dtype} {tuple(segments.shape)}")
    if segments.device != points.device:
        raise ValueError(f"{op}: segments is on {segments.device} but points are on {points.device}")
    if int(segments[0]) != 0 or int(segments[-1]) != points.shape[0] or bool((segments.diff() < 0).any()):
        raise ValueError(f"{op}: segments must rise from 0 to the number of rows ({points.shape[0]}), got "
                         f"{segments.tolist() if segments.shape[0] <= 20 else 'other values'}")
    return segments.contiguous()
