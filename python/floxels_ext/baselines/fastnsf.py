"""Fast Neural Scene Flow (FastNSF; Li, Zheng, Ferroni, Kaesemodel Pontes, Lucey, ICCV 2023).

The NSFP coordinate MLP, fitted to a correspondence-free loss: the distance transform of
the target scan, looked up at the warped source points, ``mean_i DT_{S1}(p_i + f(p_i))``.
The DT is built once per frame with our exact EDT op and queried with our fused, autograd-
enabled ``dt_loss`` op (trilinear, border clamped), so no nearest-neighbour search is needed.
"""

from __future__ import annotations

import time

import torch

from floxels_ext.ops import distance_transform, grid_for_points, ops_ns
from floxels_ext.baselines.config import FastNSFConfig
from floxels_ext.baselines.mlp import CoordinateMLP
from floxels_ext.baselines._common import BaselineResult, finish, optimise, prepare_pair, subsample, sync, trivial_result


def target_distance_transform(source: torch.Tensor, target: torch.Tensor, cfg: FastNSFConfig):
    """(DT values (Z, Y, X) float32, origin) of ``target`` on a lattice covering both clouds
    (as FastNSF does: warped source points stay inside it unless they move far)."""
    origin, shape = grid_for_points(torch.cat([source, target]), cfg.dt_cell, cfg.dt_padding, cfg.max_dt_cells)
    return distance_transform(target, cfg.dt_cell, origin=origin, grid_shape=shape)


def fit_fastnsf(source, target, config: FastNSFConfig | None = None, device=None) -> BaselineResult:
    """FastNSF flow of every point of ``source`` towards ``target`` with the loss history and
    timings. See :func:`estimate_flow_fastnsf`."""
    cfg = config or FastNSFConfig()
    if not isinstance(cfg, FastNSFConfig):
        raise TypeError(f"config must be a FastNSFConfig, got {type(cfg).__name__}")
    t_start = time.perf_counter()
    prep = prepare_pair(source, target, device)
    trivial = trivial_result(prep, "fastnsf")
    if trivial is not None:
        return trivial
    src, tgt = prep.points
    t0 = time.perf_counter()
    dt, origin = target_distance_transform(src, tgt, cfg)
    sync(src)
    timings = {"dt": time.perf_counter() - t0}
    src_opt = subsample(src, cfg.max_points, cfg.seed).contiguous()
    net = CoordinateMLP(cfg.num_layers, cfg.hidden_units, cfg.activation, cfg.init, cfg.seed).to(src.device)

    # The raw autograd-enabled op (torch.ops.floxels.dt_loss): the public wrapper would re-check
    # every iteration that the inputs are finite (a reduction plus a host sync); a diverging
    # MLP shows up as a non-finite loss, which the loop handles.
    args = (origin, float(cfg.dt_cell), [1.0], [1.0], float(cfg.truncation))

    def loss_fn():
        return ops_ns.dt_loss(src_opt, net(src_opt).contiguous(), [dt], *args)

    t0 = time.perf_counter()
    losses, best_iter = optimise(list(net.parameters()), loss_fn, cfg, "fastnsf")
    sync(src)
    timings["optimise"] = time.perf_counter() - t0
    return finish(net, src, prep, losses, best_iter, timings, t_start)


def estimate_flow_fastnsf(source, target, config: FastNSFConfig | None = None, device=None):
    """FastNSF flow (metres per frame step) of every point of ``source`` towards ``target``.

    Same input/output conventions as :func:`floxels_ext.baselines.estimate_flow_nsfp`.
    """
    return fit_fastnsf(source, target, config, device).flow
