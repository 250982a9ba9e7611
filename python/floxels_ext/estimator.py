"""The Floxels estimator: public API and the optimisation loop on top of torch.ops.floxels.

One frame:
1. an exact distance transform (0.1 m samples) of every support scan, cached per scan so
   sliding windows (:func:`estimate_sequence`) build each one once;
2. DBSCAN clusters of the target scan (our exact op: labels identical to scikit-learn);
3. Adam over the flow-grid vertices touched by the target points (see
   ``floxels_ext.ops.corners``: exactly dense Adam, at a fraction of the cost), each
   iteration being: compact gather of the point flow, fused multi-scan DT loss +
   gradient, fused cluster-consistency loss + gradient, flow-norm term, compact scatter;
4. early stopping; the result is the flow of the lowest loss seen.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import torch

from .config import FloxelsConfig
from .early_stopping import EarlyStopping
from .ops import compact_corners, dbscan, distance_transform, grid_for_points
from .ops.corners import CompactCorners
from .scans import PreparedScans, prepare_scans, restore_output

F = torch.ops.floxels


@dataclass
class DistanceTransform:
    """A support scan's distance transform: float32 (Z, Y, X) metres, sample (0,0,0) at ``origin``."""

    values: torch.Tensor
    origin: list[float]


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

    @property
    def grid(self) -> torch.Tensor | None:
        """Dense (3, Z, Y, X) flow grid (vertex (iz,iy,ix) at grid_origin + (ix,iy,iz)*voxel_size);
        vertices no point touches hold 0."""
        if self._corners is None:
            return None
        return self._corners.to_dense(self._params)


def _build_dt(points: torch.Tensor, cfg: FloxelsConfig) -> DistanceTransform | None:
    if points.shape[0] == 0:
        return None
    values, origin = distance_transform(points, cfg.dt_cell, cfg.dt_padding, max_cells=cfg.max_dt_cells)
    return DistanceTransform(values, origin)


class Floxels:
    """Floxels scene-flow estimator.

    >>> est = Floxels(FloxelsConfig(max_iters=300), device="cpu")
    >>> res = est.fit(scans, target=2)      # res.flow, res.losses, res.labels, res.grid, res.timings
    """

    def __init__(self, config: FloxelsConfig | None = None, device=None) -> None:
        if config is not None and not isinstance(config, FloxelsConfig):
            raise TypeError(f"config must be a FloxelsConfig, got {type(config).__name__}")
        self.config = config or FloxelsConfig()
        self.device = device

    # -- public -----------------------------------------------------------------------
    def fit(self, scans: Sequence, target: int | None = None,
            dt_cache: dict[int, DistanceTransform | None] | None = None) -> FloxelsResult:
        """Estimate the flow of ``scans[target]`` (default: the middle scan).

        ``dt_cache`` maps scan index -> distance transform and is filled in place, so that
        callers optimising several targets over the same scans build each DT once.
        """
        prep = prepare_scans(scans, target, self.device)
        return self._fit_prepared(prep, dt_cache if dt_cache is not None else {})

    # -- internals ----------------------------------------------------------------------
    def _fit_prepared(self, prep: PreparedScans, dt_cache: dict) -> FloxelsResult:
        cfg = self.config
        timings: dict[str, float] = {}
        t_start = time.perf_counter()
        P = prep.points[prep.target]
        if P.shape[0] == 0:
            empty = P.new_zeros(0, 3)
            return FloxelsResult(restore_output(empty, prep), empty, None, timings=timings,
                                 voxel_size=cfg.voxel_size)

        t0 = time.perf_counter()
        dts, origins, offsets, weights = [], [], [], []
        for i, t in zip(prep.supports, prep.offsets):
            if i not in dt_cache:
                dt_cache[i] = _build_dt(prep.points[i], cfg)
            d = dt_cache[i]
            if d is None:  # empty support scan: no evidence from it
                continue
            dts.append(d.values)
            origins.extend(d.origin)
            offsets.append(float(t))
            weights.append(cfg.lambda_d * cfg.time_weight(t))
        _sync(P)
        timings["dt"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        labels = dbscan(P, cfg.dbscan_eps, cfg.dbscan_min_samples) if cfg.cluster_loss else None
        timings["dbscan"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        g_origin, g_shape = grid_for_points(P, cfg.voxel_size, cfg.voxel_size, max_cells=1 << 40)
        # Sort points along the flow grid so neighbouring points touch neighbouring memory
        # (flow vertices and DT samples) in every kernel.
        key = _voxel_key(P, g_origin, cfg.voxel_size, g_shape)
        order = torch.argsort(key)
        Ps = P[order].contiguous()
        lab_s = labels[order].contiguous() if labels is not None else None
        corners = compact_corners(Ps, g_origin, cfg.voxel_size, g_shape)
        params, losses, best_iter = self._optimise(Ps, corners, lab_s, dts, origins, offsets, weights,
                                                   len(prep.supports))
        flow_s = F.corner_gather(params, corners.corner_idx, corners.corner_w)
        flow = torch.empty_like(flow_s)
        flow[order] = flow_s
        _sync(P)
        timings["optimise"] = time.perf_counter() - t0
        timings["total"] = time.perf_counter() - t_start

        # keep the grid view consistent with the caller's point order
        return FloxelsResult(restore_output(flow, prep), flow, labels, losses, best_iter, len(losses), timings,
                             g_origin, cfg.voxel_size, corners, params)

    def _optimise(self, P, corners, labels, dts, origins, offsets, weights, num_support):
        cfg = self.config
        n = P.shape[0]
        M = corners.num_params
        idx, cw = corners.corner_idx, corners.corner_w
        theta = torch.zeros(M, 3, dtype=P.dtype, device=P.device)
        adam = _Adam(theta, cfg)
        scale = cfg.regulariser_scale(num_support)
        ncl = 0
        if labels is not None and labels.numel():
            ncl = int(labels.max()) + 1
        use_cluster = labels is not None and ncl > 0
        stopper = EarlyStopping(cfg.patience, cfg.min_delta)
        best = theta.detach().clone()
        losses: list[float] = []
        for it in range(cfg.max_iters):
            with torch.no_grad():
                f = F.corner_gather(theta, idx, cw)
                if dts:
                    loss, g = F.dt_loss_fwd_bwd(P, f, dts, origins, cfg.dt_cell, offsets, weights, cfg.truncation)
                else:
                    loss, g = f.new_zeros(()), torch.zeros_like(f)
                if use_cluster:
                    lc, gc = F.cluster_consistency_fwd_bwd(f, labels, ncl)
                    loss = loss + (scale * cfg.lambda_c) * lc
                    g.add_(gc, alpha=scale * cfg.lambda_c)
                if cfg.flow_norm_loss:
                    lam = scale * cfg.lambda_g(it)
                    norms = torch.linalg.vector_norm(f, dim=1)
                    loss = loss + lam * norms.sum() / n
                    # d||f||/df = f/||f||, taken as 0 at f = 0 (the zero initialisation)
                    g.addcdiv_(f, norms.clamp_min(1e-12).unsqueeze(1), value=lam / n)
                value = loss.item()
                losses.append(value)
                is_best, stop = stopper.update(value, it)
                if is_best:
                    best.copy_(theta)
                if stop or it == cfg.max_iters - 1:
                    break
                adam.step(F.corner_scatter(g, idx, cw, M))
        return best, losses, stopper.best_iter


class _Adam:
    """Adam (no weight decay, no amsgrad) with torch.optim.Adam's exact update formula,
    written out in place: the first ``torch.optim.Adam.step`` costs ~1 s of lazy imports,
    more than a whole CPU frame's optimisation."""

    def __init__(self, param: torch.Tensor, cfg: FloxelsConfig) -> None:
        self.p, self.lr, self.eps = param, cfg.lr, cfg.adam_eps
        self.b1, self.b2 = cfg.adam_betas
        self.m = torch.zeros_like(param)
        self.v = torch.zeros_like(param)
        self.t = 0

    def step(self, grad: torch.Tensor) -> None:
        self.t += 1
        self.m.lerp_(grad, 1 - self.b1)
        self.v.mul_(self.b2).addcmul_(grad, grad, value=1 - self.b2)
        denom = (self.v.sqrt() / math.sqrt(1 - self.b2 ** self.t)).add_(self.eps)
        self.p.addcdiv_(self.m, denom, value=-self.lr / (1 - self.b1 ** self.t))


def _voxel_key(P, origin, spacing, shape) -> torch.Tensor:
    Z, Y, X = shape
    o = torch.tensor(origin, dtype=P.dtype, device=P.device)
    i = ((P - o) / spacing).floor().long()
    return (i[:, 2].clamp(0, Z - 1) * Y + i[:, 1].clamp(0, Y - 1)) * X + i[:, 0].clamp(0, X - 1)


def _sync(t: torch.Tensor) -> None:
    if t.is_cuda:
        torch.cuda.synchronize(t.device)


def estimate_flow(scans: Sequence, target: int | None = None, config: FloxelsConfig | None = None, device=None):
    """Flow (per frame step) of every point of ``scans[target]``.

    ``scans``: 2 to 13 (N_i, 3) float arrays/tensors in one ego-motion-compensated frame,
    consecutive at the sensor rate; ``target`` defaults to the middle scan, every other scan
    is a support scan at time offset ``index - target``. Returns (N_target, 3): numpy
    float32 for numpy input, else a tensor of the input's dtype on the input's device.
    Rows with NaN/inf coordinates are dropped (with a warning) and get NaN flow.
    """
    return Floxels(config, device).fit(scans, target).flow


def window_for(frame: int, num_frames: int, num_scans: int) -> tuple[int, int]:
    """[start, stop) of the window of ``num_scans`` scans used for ``frame``: centred on it,
    shifted inwards at the ends of the sequence (so the target may be the first/last scan)."""
    w = min(num_scans, num_frames)
    start = min(max(frame - w // 2, 0), num_frames - w)
    return start, start + w


def estimate_sequence(scans: Sequence, config: FloxelsConfig | None = None, device=None,
                      frames: Sequence[int] | None = None,
                      callback: Callable[[int, FloxelsResult], None] | None = None) -> list:
    """Flow of every frame of a sequence (or of ``frames``) with a sliding window of
    ``config.num_scans`` scans. Each scan's distance transform is built once and reused by
    every window that needs it (and freed once no later window does).

    Returns a list with one flow per requested frame (numpy float32 for numpy input).
    ``callback(frame, result)`` is called after each frame (e.g. to write it to disk).
    """
    cfg = config or FloxelsConfig()
    scans = list(scans)
    n = len(scans)
    if n < 2:
        raise ValueError(f"a sequence needs at least 2 scans, got {n}")
    frames = list(range(n)) if frames is None else [int(f) for f in frames]
    for f in frames:
        if not 0 <= f < n:
            raise IndexError(f"frame {f} is out of range for {n} scans")
    est = Floxels(cfg, device)
    cache: dict[int, DistanceTransform | None] = {}
    out = []
    for k, f in enumerate(frames):
        start, stop = window_for(f, n, cfg.num_scans)
        window_cache = {i - start: cache[i] for i in range(start, stop) if i in cache}
        res = est.fit(scans[start:stop], target=f - start, dt_cache=window_cache)
        for j, d in window_cache.items():
            cache[start + j] = d
        # free DTs that no later window will use
        later = [window_for(g, n, cfg.num_scans)[0] for g in frames[k + 1:]]
        horizon = min(later) if later else math.inf
        for i in [i for i in cache if i < horizon]:
            del cache[i]
        out.append(res.flow)
        if callback is not None:
            callback(f, res)
    return out
