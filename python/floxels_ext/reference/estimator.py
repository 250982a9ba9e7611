"""A straightforward pure-PyTorch implementation of Floxels, used as the baseline.

It is what one writes directly from the paper: scipy's EDT per support scan, scikit-learn
DBSCAN, a dense ``nn.Parameter`` voxel grid read with ``grid_sample``, the losses in
eager PyTorch with autograd, and ``torch.optim.Adam``. The benchmarks and tests compare
:func:`floxels_ext.estimate_flow` against it for speed and accuracy. It shares only input
handling, the config and the early-stopping rule with the fast path.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from floxels_ext.estimator.config import FloxelsConfig
from floxels_ext.estimator.early_stopping import EarlyStopping
from floxels_ext.ops.grid import grid_for_points
from floxels_ext.estimator.scans import prepare_scans, restore_output


def _normalised(q: torch.Tensor, origin: Sequence[float], spacing: float, shape_zyx) -> torch.Tensor:
    """Points -> grid_sample coordinates in [-1, 1] (align_corners=True), as (1, 1, 1, N, 3)."""
    o = torch.tensor(origin, dtype=q.dtype, device=q.device)
    size = torch.tensor([shape_zyx[2], shape_zyx[1], shape_zyx[0]], dtype=q.dtype, device=q.device)
    g = 2.0 * (q - o) / (spacing * (size - 1)) - 1.0
    return g.view(1, 1, 1, -1, 3)


def _sample(volume: torch.Tensor, q: torch.Tensor, origin, spacing) -> torch.Tensor:
    """Trilinear look-up of a (1, C, Z, Y, X) volume at points q (N, 3) -> (N, C)."""
    out = F.grid_sample(volume, _normalised(q, origin, spacing, volume.shape[2:]),
                        mode="bilinear", padding_mode="border", align_corners=True)
    return out.view(volume.shape[1], -1).T


def scipy_distance_transform(points: torch.Tensor, cell: float, padding: float, max_cells: int):
    """EDT of a scan with scipy (metres, float32 tensor (Z, Y, X)) and its lattice origin."""
    from scipy.ndimage import distance_transform_edt

    origin, shape = grid_for_points(points, cell, padding, max_cells)
    occ = np.zeros(shape, dtype=bool)
    idx = np.floor((points.cpu().numpy() - np.array(origin)) / cell + 0.5).astype(np.int64)
    ok = np.all((idx >= 0) & (idx < np.array(shape[::-1])), axis=1)
    idx = idx[ok]
    occ[idx[:, 2], idx[:, 1], idx[:, 0]] = True
    dt = distance_transform_edt(~occ, sampling=cell).astype(np.float32)
    return torch.from_numpy(dt), origin


def sklearn_dbscan_labels(points: torch.Tensor, eps: float, min_samples: int) -> torch.Tensor:
    """DBSCAN cluster labels (int64, -1 = noise) of ``points`` with scikit-learn, on the points' device."""
    n = points.shape[0]
    if n == 0:
        return torch.empty(0, dtype=torch.int64, device=points.device)
    from sklearn.cluster import DBSCAN  # imported lazily: sklearn import costs ~0.5 s

    lab = DBSCAN(eps=eps, min_samples=min_samples, algorithm="auto").fit(points.detach().cpu().numpy()).labels_
    return torch.from_numpy(lab.astype(np.int64)).to(points.device)


def reference_estimate_flow(scans: Sequence, target: int | None = None, config: FloxelsConfig | None = None,
                            device=None, return_info: bool = False):
    """Floxels flow of ``scans[target]`` computed the straightforward way (see module doc)."""
    cfg = config or FloxelsConfig()
    prep = prepare_scans(scans, target, device)
    dev = prep.points[0].device
    timings = {}
    P = prep.points[prep.target]
    n = P.shape[0]
    if n == 0:
        out = restore_output(P.new_zeros(0, 3), prep)
        return (out, {"timings": timings, "losses": []}) if return_info else out

    t0 = time.perf_counter()
    dts = []
    for i, t in zip(prep.supports, prep.offsets):
        pts = prep.points[i]
        if pts.shape[0] == 0:
            continue
        dt, origin = scipy_distance_transform(pts, cfg.dt_cell, cfg.dt_padding, cfg.max_dt_cells)
        dts.append((dt.to(dev)[None, None], origin, float(t), cfg.time_weight(t)))
    timings["dt"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    labels = sklearn_dbscan_labels(P, cfg.dbscan_eps, cfg.dbscan_min_samples) if cfg.cluster_loss else None
    timings["dbscan"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    g_origin, g_shape = grid_for_points(P, cfg.voxel_size, cfg.voxel_size, max_cells=1 << 31)
    grid = torch.nn.Parameter(torch.zeros(1, 3, *g_shape, device=dev))
    opt = torch.optim.Adam([grid], lr=cfg.lr, betas=cfg.adam_betas, eps=cfg.adam_eps)
    scale = cfg.regulariser_scale(len(prep.supports), prep.offsets)
    if labels is not None:
        keep = labels >= 0
        lab = labels[keep]
        ncl = int(lab.max()) + 1 if lab.numel() else 0
        counts = torch.bincount(lab, minlength=ncl).clamp(min=1).float()[:, None]
    stopper = EarlyStopping(cfg.patience, cfg.min_delta)
    best_flow = torch.zeros_like(P)
    losses = []
    trunc_above = cfg.truncation if cfg.truncation_mode == "clamp" else 0.0
    for it in range(cfg.max_iters):
        for group in opt.param_groups:  # lr schedule (FloxelsConfig.lr_milestones)
            group["lr"] = cfg.lr_at(it)
        opt.zero_grad(set_to_none=True)
        flow = _sample(grid, P, g_origin, cfg.voxel_size)
        loss = flow.new_zeros(())
        for dt, origin, t, w in dts:
            v = _sample(dt, P + t * flow, origin, cfg.dt_cell)[:, 0]
            loss = loss + cfg.lambda_d * w * torch.where(v < cfg.truncation, v, torch.full_like(v, trunc_above)).mean()
        if labels is not None and ncl > 0:
            means = flow.new_zeros(ncl, 3).index_add(0, lab, flow[keep]) / counts
            d = flow[keep] - means[lab]
            sq = (d * d).sum(1)
            nz = sq > 0
            norms = torch.where(nz, torch.sqrt(torch.where(nz, sq, torch.ones_like(sq))), torch.zeros_like(sq))
            n_c = n if cfg.cluster_loss_mean == "all" else max(int(keep.sum()), 1)
            loss = loss + scale * cfg.lambda_c * norms.sum() / n_c
        if cfg.flow_norm_loss:
            sq = (flow * flow).sum(1)
            nz = sq > 0
            norms = torch.where(nz, torch.sqrt(torch.where(nz, sq, torch.ones_like(sq))), torch.zeros_like(sq))
            loss = loss + scale * cfg.lambda_g(it) * norms.mean()
        value = loss.item()
        losses.append(value)
        is_best, stop = stopper.update(value, it)
        if is_best:
            best_flow = flow.detach().clone()
        if stop:
            break
        loss.backward()
        opt.step()
    timings["optimise"] = time.perf_counter() - t0
    out = restore_output(best_flow, prep)
    if return_info:
        return out, {"timings": timings, "losses": losses, "best_iter": stopper.best_iter, "labels": labels}
    return out
