"""Shared plumbing of the MLP baselines: input validation, subsampling, the Adam loop with
early stopping and lowest-loss tracking, and the result record."""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import torch

from ..early_stopping import EarlyStopping
from ..scans import PreparedScans, prepare_scans, restore_output


@dataclass
class BaselineResult:
    """What one baseline optimisation produced."""

    flow: object                       # (N_source, 3): numpy float32 or tensor, like the input
    flow_tensor: torch.Tensor          # (N_kept, 3) float32 on the compute device (finite rows)
    losses: list[float] = field(default_factory=list)  # loss per iteration
    best_iter: int = -1                # iteration whose network gives the flow
    num_iters: int = 0
    timings: dict[str, float] = field(default_factory=dict)  # seconds per stage


def prepare_pair(source, target, device) -> PreparedScans:
    """Validate and move a (source, target) pair like the Floxels estimator does (NaN rows
    dropped with a warning and returned as NaN flow; numpy in -> numpy out)."""
    try:
        return prepare_scans([source, target], 0, device)
    except (TypeError, ValueError, IndexError) as e:
        # prepare_scans numbers the scans; name them for this two-scan API
        msg = str(e).replace("scan 0", "source").replace("scan 1", "target")
        raise type(e)(msg) from None


def subsample(points: torch.Tensor, max_points: int, seed: int) -> torch.Tensor:
    if max_points <= 0 or points.shape[0] <= max_points:
        return points
    g = torch.Generator().manual_seed(seed)
    idx = torch.randperm(points.shape[0], generator=g)[:max_points].to(points.device)
    return points[idx]


def sync(t: torch.Tensor) -> None:
    if t.is_cuda:
        torch.cuda.synchronize(t.device)


def trivial_result(prep: PreparedScans, method: str) -> BaselineResult | None:
    """Result for an empty source (empty flow) or an empty target (zero flow: no evidence)."""
    src, tgt = prep.points[0], prep.points[1]
    if src.shape[0] == 0:
        flow = src.new_zeros(0, 3)
    elif tgt.shape[0] == 0:
        warnings.warn(f"{method}: the target scan has no (finite) points; returning zero flow",
                      UserWarning, stacklevel=3)
        flow = torch.zeros_like(src)
    else:
        return None
    return BaselineResult(restore_output(flow, prep), flow)


def optimise(params: list[torch.Tensor], loss_fn: Callable[[], torch.Tensor], cfg, method: str):
    """Adam on ``params`` minimising ``loss_fn()``; returns (losses, best_iter) and leaves the
    parameters of the lowest loss seen in ``params``.

    Early stopping as in NSFP/FastNSF (and :class:`floxels_ext.early_stopping.EarlyStopping`):
    stop after ``patience`` iterations without an improvement of more than ``min_delta``.
    """
    opt = torch.optim.Adam(params, lr=cfg.lr, betas=tuple(cfg.adam_betas), eps=cfg.adam_eps,
                           weight_decay=cfg.weight_decay)
    stopper = EarlyStopping(cfg.patience, cfg.min_delta)
    best = [p.detach().clone() for p in params]
    losses: list[float] = []
    for it in range(cfg.max_iters):
        opt.zero_grad(set_to_none=True)
        loss = loss_fn()
        value = loss.item()
        if not math.isfinite(value):
            warnings.warn(f"{method}: non-finite loss at iteration {it}; keeping the best flow so far",
                          UserWarning, stacklevel=3)
            break
        losses.append(value)
        is_best, stop = stopper.update(value, it)
        if is_best:
            with torch.no_grad():
                for b, p in zip(best, params):
                    b.copy_(p)
        if (cfg.early_stopping and stop) or it == cfg.max_iters - 1:
            break
        loss.backward()
        opt.step()
    with torch.no_grad():
        for p, b in zip(params, best):
            p.copy_(b)
    return losses, stopper.best_iter


def finish(net, src: torch.Tensor, prep: PreparedScans, losses, best_iter, timings, t_start) -> BaselineResult:
    """Flow of every kept source point from the (best) network, converted like the input."""
    with torch.no_grad():
        flow = net(src).contiguous()
    sync(flow)
    timings["total"] = time.perf_counter() - t_start
    return BaselineResult(restore_output(flow, prep), flow, losses, best_iter, len(losses), timings)
