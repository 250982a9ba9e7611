"""The estimator's DBSCAN sized from each target's known bounds (``floxels::dbscan_in_bounds``,
``group._targets``): in a group of targets of different extents each gets its own bounds (the
same labels as DBSCAN of that target alone), and bounds that do not hold are refused after
the set-up's synchronisation, never used."""

import numpy as np
import pytest
import torch

import floxels_ext.estimator.group as group
from floxels_ext import Floxels, FloxelsConfig, ops

CFG = FloxelsConfig(max_iters=10, patience=40)


def _window(seed, scale):
    rng = np.random.default_rng(seed)
    base = np.concatenate([rng.normal(c, 0.2, (150, 3)) for c in rng.uniform(-scale, scale, (5, 3))])
    return [(base + [0.05 * k, 0.0, 0.0]).astype(np.float32) for k in range(3)]


def test_each_target_of_a_group_gets_its_own_bounds():
    small, wide = _window(0, 3.0), _window(1, 40.0)
    res = Floxels(CFG, "cpu").fit_many([(small, 1), (wide, 1), (small[::-1], 1)])
    for r, w in zip(res, (small, wide, small[::-1])):
        want = ops.dbscan(torch.from_numpy(w[1]), CFG.dbscan_eps, CFG.dbscan_min_samples)
        assert torch.equal(r.labels.cpu(), want)  # (labels of the kept rows, in the input's order)


def test_bounds_that_do_not_hold_are_refused(monkeypatch):
    known = group.known_bounds

    def shrunk(prep, i):
        b = known(prep, i)
        if i != prep.target:
            return b
        lo, hi = (np.asarray(x, dtype=np.float64) for x in (b if b is not None else group.point_bounds(
            [prep.points[i]])[0]))
        return lo + 0.5, hi - 0.5

    monkeypatch.setattr(group, "known_bounds", shrunk)
    with pytest.raises(RuntimeError, match="outside the bounds"):
        Floxels(CFG, "cpu").fit(_window(2, 5.0), 1)
