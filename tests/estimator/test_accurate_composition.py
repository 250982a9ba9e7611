"""How the ``accurate`` preset composes its ingredients (estimator/group.py): the evidence test
judges the optimiser's flow *before* the rigid refinement (which may then not revive a group
without evidence), and ``refine_max_supports`` limits the refinement to few-scan windows."""

import numpy as np
import pytest

from floxels_ext.estimator.api import Floxels
from floxels_ext.estimator.config import FloxelsConfig
from test_refine import passing_cars, sliding_box


def _fit(scans, target, **cfg):
    return Floxels(FloxelsConfig(**cfg), device="cpu").fit(scans, target)


def test_refine_max_supports_gates_the_refinement_by_window_size():
    scans, _ = sliding_box(0.8, (-1, 0, 1))  # 2 support scans
    off = _fit(scans, 1, num_scans=3).flow
    on = _fit(scans, 1, num_scans=3, rigid_refine=True).flow
    assert not np.array_equal(on, off)  # the refinement changes this window...
    assert np.array_equal(_fit(scans, 1, num_scans=3, rigid_refine=True, refine_max_supports=2).flow, on)
    # ...and is skipped where the window has more support scans than allowed
    assert np.array_equal(_fit(scans, 1, num_scans=3, rigid_refine=True, refine_max_supports=1).flow, off)


def test_evidence_verdict_is_the_optimiser_flows():
    # the refinement runs after the test: the per-point evidence is the same with it or without
    scans, _ = passing_cars(0.9, (-1, 0, 1))
    a = _fit(scans, 1, num_scans=3, evidence="zero")
    b = _fit(scans, 1, num_scans=3, evidence="zero", rigid_refine=True)
    assert np.array_equal(a.evidence, b.evidence) and np.array_equal(a.explained, b.explained)
    # and a group the test rejected keeps zero flow after the refinement
    rejected = ~np.asarray(b.explained, dtype=bool)
    assert rejected.any() and np.all(b.flow[rejected] == 0)


def test_refine_max_supports_must_not_be_negative():
    with pytest.raises(ValueError, match="refine_max_supports"):
        FloxelsConfig(refine_max_supports=-1)
