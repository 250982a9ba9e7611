"""Issue 31: the preparation ops have no float atomics, but order-dependent results (DBSCAN's
union-find with CAS, the nearest neighbour's 64-bit atomicMin, the problem setup's sorts and
counts) would show here: each runs twice and must give the same bytes. The CPU run checks
the test itself; the CUDA run needs a GPU (device tool)."""

import pytest
import torch

from floxels_ext import FloxelsConfig, ops

from test_determinism_solver_ops import _hot_points, _same


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)])
def test_preparation_ops_are_deterministic(device):
    cfg = FloxelsConfig()
    P = _hot_points(20_000, torch.float32, seed=2, device=device)
    Q = (P + 0.05).contiguous()

    def run():
        lab = ops.dbscan(P, cfg.dbscan_eps, cfg.dbscan_min_samples)
        d, o = ops.distance_transform(Q, cfg.dt_cell, cfg.dt_padding)
        nn = ops.nearest_neighbor(P, Q)
        go, gs = ops.grid_for_points(P.cpu(), cfg.voxel_size, cfg.voxel_size)
        st = ops.problem_setup(P, lab, go, cfg.voxel_size, gs, 32)
        return [lab, d, torch.tensor(o), nn, st.order, st.points, st.corners.corner_idx, st.corners.corner_w,
                *st.segments]

    for a, b in zip(run(), run()):
        _same(a, b)
