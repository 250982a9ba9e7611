"""Shared plumbing of the MLP baselines: input validation, subsampling, the Adam loop with
early stopping and lowest-loss tracking, and the result record."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import torch

from floxels_ext.estimator.scans import PreparedScans, prepare_scans, restore_output
from floxels_ext.estimator.user_warnings import warn_user


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
        warn_user(f"{method}: the target scan has no (finite) points; returning zero flow")
        flow = torch.zeros_like(src)
    else:
        return None
    return BaselineResult(restore_output(flow, prep), flow)


#: Iterations between two host read-backs of the device-side stopping flag (the only host
#: synchronisation of the loop). Up to this many iterations run after the stop; they change
#: neither the recorded losses nor the kept (best) parameters.
CHECK_EVERY = 64


def _masked_copy(dst: list[torch.Tensor], src: list[torch.Tensor], w: torch.Tensor) -> None:
    """dst <- src where the 0-dim ``w`` is 1, unchanged where 0 (lerp with weight 1 returns the
    end point exactly), without reading ``w`` on the host."""
    src = [p.detach() for p in src]
    try:
        torch._foreach_lerp_(dst, src, w)
    except (TypeError, RuntimeError, NotImplementedError):  # older builds: no tensor-weight overload
        for d, s in zip(dst, src):
            d.lerp_(s, w)


def optimise(params: list[torch.Tensor], loss_fn: Callable[[], torch.Tensor], cfg, method: str):
    """Adam on ``params`` minimising ``loss_fn()``; returns (losses, best_iter) and leaves the
    parameters of the lowest loss seen in ``params``.

    Early stopping as in NSFP/FastNSF (and :class:`floxels_ext.estimator.early_stopping.EarlyStopping`):
    stop after ``patience`` iterations without an improvement of more than ``min_delta``; a
    non-finite loss stops too (not recorded). The bookkeeping runs on the device (0-dim
    tensors, the lowest-loss parameters copied by a masked lerp), so iterations do not wait for
    the host; the host reads the stop flag every :data:`CHECK_EVERY` iterations. Iterations run
    after the stop are masked out of the record and the best copy, so the result is the same
    as stopping at once.
    """
    dev = params[0].device
    fused = dev.type == "cuda"  # one kernel for the whole Adam step
    opt = torch.optim.Adam(params, lr=cfg.lr, betas=tuple(cfg.adam_betas), eps=cfg.adam_eps,
                           weight_decay=cfg.weight_decay, **({"fused": True} if fused else {}))
    best_params = [p.detach().clone() for p in params]
    f64 = dict(dtype=torch.float64, device=dev)
    history = torch.zeros(cfg.max_iters, **f64)
    best = torch.tensor(math.inf, **f64)        # lowest loss seen
    ref = torch.tensor(math.inf, **f64)         # last loss that improved by min_delta
    stale = torch.zeros((), **f64)
    best_iter = torch.full((), -1.0, **f64)
    recorded = torch.zeros((), **f64)           # losses recorded (= iterations before the stop)
    stopped = torch.zeros((), dtype=torch.bool, device=dev)
    nonfinite = torch.zeros((), dtype=torch.bool, device=dev)
    patience = float(cfg.patience) if cfg.early_stopping else math.inf
    for it in range(cfg.max_iters):
        opt.zero_grad(set_to_none=True)
        loss = loss_fn()
        with torch.no_grad():
            lv = loss.detach().to(torch.float64)
            live = ~stopped
            finite = torch.isfinite(lv)
            rec = live & finite
            history[it] = torch.where(rec, lv, history[it])
            is_best = rec & (lv < best)
            best.copy_(torch.where(is_best, lv, best))
            best_iter.copy_(torch.where(is_best, float(it), best_iter))
            improved = rec & (lv < ref - cfg.min_delta)
            ref.copy_(torch.where(improved, lv, ref))
            stale.copy_(torch.where(improved, 0.0, stale + rec.to(stale.dtype)))
            recorded.add_(rec.to(recorded.dtype))
            nonfinite.logical_or_(live & ~finite)
            stopped.logical_or_((live & ~finite) | (rec & (stale >= patience)))
            # best <- params where is_best (lerp weight 1 gives p exactly, weight 0 keeps best)
            _masked_copy(best_params, params, is_best.to(params[0].dtype))
        if it == cfg.max_iters - 1 or ((it + 1) % CHECK_EVERY == 0 and bool(stopped)):
            break
        loss.backward()
        opt.step()
    with torch.no_grad():
        for p, b in zip(params, best_params):
            p.copy_(b)
    n = int(recorded.item())
    if bool(nonfinite):
        warn_user(f"{method}: non-finite loss at iteration {n}; keeping the best flow so far")
    return history[:n].tolist(), int(best_iter.item())


def finish(net, src: torch.Tensor, prep: PreparedScans, losses, best_iter, timings, t_start) -> BaselineResult:
    """Flow of every kept source point from the (best) network, converted like the input."""
    with torch.no_grad():
        flow = net(src).contiguous()
    sync(flow)
    timings["total"] = time.perf_counter() - t_start
    return BaselineResult(restore_output(flow, prep), flow, losses, best_iter, len(losses), timings)
