"""A frame's host time is named part by part (issue 42: 13 ms a frame went to work no bench
named): FloxelsResult.timings holds every part of estimator/result.py's HOST_PARTS, and
Floxels.fit's "whole" is their sum plus a small "other"."""

import numpy as np

from floxels_ext import Floxels, FloxelsConfig
from floxels_ext.estimator.result import HOST_PARTS


def test_named_parts_sum_to_the_whole_call():
    rng = np.random.default_rng(0)
    scans = [rng.uniform(-8, 8, (600, 3)).astype(np.float32) + k * 0.1 for k in range(3)]
    res = Floxels(FloxelsConfig(max_iters=15), "cpu").fit(scans, 1)
    t = res.timings
    assert set(HOST_PARTS) <= set(t) and {"whole", "other"} <= set(t)
    assert all(t[k] >= 0 for k in HOST_PARTS)
    named = sum(t[k] for k in HOST_PARTS)
    assert abs(t["whole"] - named - t["other"]) < 1e-9
    assert 0 <= t["other"] <= 0.1 * t["whole"] + 1e-3
    assert t["solve"] > 0  # on the CPU the optimisation itself
