"""Cluster reductions (per-cluster mean, cluster-consistency loss): registration and wrappers."""

from __future__ import annotations

import torch

from floxels_ext.ops._checks import require_tensors, same_device
from floxels_ext.ops._lib import ops_ns


@torch.library.register_fake("floxels::cluster_mean")
def _mean_fake(values, labels, num_clusters):
    return values.new_empty((num_clusters, values.shape[1]))


@torch.library.register_fake("floxels::cluster_consistency_loss")
def _loss_fake(flow, labels, num_clusters):
    return flow.new_empty(())


@torch.library.register_fake("floxels::cluster_consistency_loss_backward")
def _loss_bwd_fake(grad, flow, labels, num_clusters):
    return torch.empty_like(flow)


@torch.library.register_fake("floxels::cluster_consistency_fwd_bwd")
def _fwd_bwd_fake(flow, labels, num_clusters):
    return flow.new_empty(()), torch.empty_like(flow)


def _mean_setup(ctx, inputs, output):
    values, labels, num_clusters = inputs
    ctx.save_for_backward(labels)
    ctx.num_clusters = num_clusters


def _mean_backward(ctx, grad):
    # d mean_c / d v_i = 1/|c| for i in c: spread each cluster's gradient back over its points.
    (labels,) = ctx.saved_tensors
    counts = torch.bincount(labels.clamp(min=0)[labels >= 0], minlength=ctx.num_clusters).clamp(min=1)
    g = (grad / counts[:, None].to(grad.dtype))[labels.clamp(min=0)]
    g = torch.where((labels >= 0)[:, None], g, torch.zeros_like(g))
    return g, None, None


def _loss_setup(ctx, inputs, output):
    flow, labels, num_clusters = inputs
    ctx.save_for_backward(flow, labels)
    ctx.num_clusters = num_clusters


def _loss_backward(ctx, grad):
    flow, labels = ctx.saved_tensors
    return ops_ns.cluster_consistency_loss_backward(grad, flow, labels, ctx.num_clusters), None, None


torch.library.register_autograd("floxels::cluster_mean", _mean_backward, setup_context=_mean_setup)
torch.library.register_autograd("floxels::cluster_consistency_loss", _loss_backward, setup_context=_loss_setup)


def _check(values, labels, num_clusters, name="values"):
    require_tensors(**{name: values, "labels": labels})
    if values.dim() != 2:
        raise ValueError(f"{name} must be (N, C), got {tuple(values.shape)}")
    if values.dtype not in (torch.float32, torch.float64):
        raise TypeError(f"{name} must be float32 or float64, got {values.dtype}")
    if labels.dim() != 1 or labels.shape[0] != values.shape[0]:
        raise ValueError(f"labels must be (N,) with N={values.shape[0]}, got {tuple(labels.shape)}")
    if labels.dtype != torch.int64:
        raise TypeError(f"labels must be int64, got {labels.dtype}")
    same_device((name, values), ("labels", labels))
    num_clusters = int(num_clusters)
    if num_clusters < 0:
        raise ValueError(f"num_clusters must be >= 0, got {num_clusters}")
    if labels.numel():
        lo, hi = int(labels.min()), int(labels.max())
        if lo < -1 or hi >= num_clusters:
            raise ValueError(f"labels must lie in [-1, {num_clusters}), got range [{lo}, {hi}]")
    return values.contiguous(), labels.contiguous(), num_clusters


def cluster_mean(values: torch.Tensor, labels: torch.Tensor, num_clusters: int) -> torch.Tensor:
    """Mean of ``values`` (N, C) per cluster (num_clusters, C); label -1 (noise) is ignored."""
    return ops_ns.cluster_mean(*_check(values, labels, num_clusters))


def cluster_consistency_loss(flow: torch.Tensor, labels: torch.Tensor, num_clusters: int) -> torch.Tensor:
    """``(1/N) sum_i ||f_i - mean flow of cluster(i)||`` (noise adds 0; gradient 0 where the norm is 0).

    A non-finite flow in a cluster makes the loss NaN (its cluster's gradient rows: 0 or NaN)."""
    return ops_ns.cluster_consistency_loss(*_check(flow, labels, num_clusters, "flow"))


def cluster_consistency_fwd_bwd(flow, labels, num_clusters):
    """(loss, d loss / d flow) of :func:`cluster_consistency_loss` in one call."""
    return ops_ns.cluster_consistency_fwd_bwd(*_check(flow, labels, num_clusters, "flow"))
