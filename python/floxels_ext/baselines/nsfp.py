"""Neural Scene Flow Prior (NSFP; Li, Kaesemodel Pontes, Lucey, NeurIPS 2021) in this framework.

A coordinate MLP f predicts the flow of every source point; a second MLP g (backward flow)
maps the warped points back. Both are fitted by Adam to the truncated Chamfer loss
``C(S0 + f, S1) + C(S0 + f - g(S0 + f), S0)`` with exact brute-force nearest neighbours.
"""

from __future__ import annotations

import time

from floxels_ext.baselines.chamfer import truncated_chamfer
from floxels_ext.baselines.config import NSFPConfig
from floxels_ext.baselines.mlp import CoordinateMLP
from floxels_ext.baselines._common import BaselineResult, finish, optimise, prepare_pair, subsample, sync, trivial_result


def _net(cfg: NSFPConfig, seed: int, device):
    return CoordinateMLP(cfg.num_layers, cfg.hidden_units, cfg.activation, cfg.init, seed).to(device)


def fit_nsfp(source, target, config: NSFPConfig | None = None, device=None) -> BaselineResult:
    """NSFP flow of every point of ``source`` towards ``target`` (one frame step), with the
    loss history and timings. See :func:`estimate_flow_nsfp`."""
    cfg = config or NSFPConfig()
    if not isinstance(cfg, NSFPConfig):
        raise TypeError(f"config must be an NSFPConfig, got {type(cfg).__name__}")
    t_start = time.perf_counter()
    prep = prepare_pair(source, target, device)
    trivial = trivial_result(prep, "nsfp")
    if trivial is not None:
        return trivial
    src, tgt = prep.points
    dev = src.device
    src_opt = subsample(src, cfg.max_points, cfg.seed)
    tgt_opt = subsample(tgt, cfg.max_points, cfg.seed + 1)
    net_f = _net(cfg, cfg.seed, dev)
    # g starts from f's initial weights, as NSFP's code does (a deep copy of f)
    net_b = _net(cfg, cfg.seed, dev) if cfg.backward_flow else None
    params = list(net_f.parameters()) + (list(net_b.parameters()) if net_b is not None else [])

    def loss_fn():
        warped = src_opt + net_f(src_opt)
        loss = truncated_chamfer(warped, tgt_opt, cfg.chamfer_truncation, cfg.chamfer_squared, cfg.nn_chunk_elems)
        if net_b is not None:
            back = warped - net_b(warped)
            loss = loss + truncated_chamfer(back, src_opt, cfg.chamfer_truncation, cfg.chamfer_squared,
                                            cfg.nn_chunk_elems)
        return loss

    t0 = time.perf_counter()
    losses, best_iter = optimise(params, loss_fn, cfg, "nsfp")
    sync(src)
    timings = {"optimise": time.perf_counter() - t0}
    return finish(net_f, src, prep, losses, best_iter, timings, t_start)


def estimate_flow_nsfp(source, target, config: NSFPConfig | None = None, device=None):
    """NSFP flow (metres per frame step) of every point of ``source`` towards ``target``.

    ``source``/``target``: (N, 3) / (M, 3) float arrays or tensors in one ego-motion-compensated
    frame. Returns (N, 3): numpy float32 for numpy input, else a tensor of the input's dtype on
    its device. Rows with NaN/inf coordinates are dropped (warning) and get NaN flow; an empty
    source gives (0, 3); an empty target gives zero flow (with a warning).
    """
    return fit_nsfp(source, target, config, device).flow
