"""Preprocessing on the shared real sweeps (issue 29; ../shared, tests/shared_data.py): the 13
raw KITTI sweeps (multipath returns metres below the road) and the Argoverse 2 pair (the
label's ground)."""

from __future__ import annotations

import numpy as np
import pytest

from floxels_ext.lidar.preprocess import (CROPPED, GROUND, KEPT, OUTLIER, Preprocess, preprocess_classes,
                                          preprocess_classes_numpy)
from shared_data import shared_path

KITTI = ("data", "kitti_raw_13f", "kitti_raw_2011_09_26_13f.npz")
AV2 = ("data", "av2_pair", "av2_7fab2350_pair.npz")


@pytest.fixture(scope="module")
def kitti():
    d = np.load(shared_path(*KITTI))
    o = d["frame_offsets"]
    return [d["points"][o[i]:o[i + 1]] for i in range(len(o) - 1)]


def _low_kept(p, cls):
    """Kept points within 0.25 m of the road level near the sensor, closer than 25 m: what a
    ring of ground left in looks like (the road is flat there in these sweeps)."""
    r = np.hypot(p[:, 0], p[:, 1])
    road = np.percentile(p[(r > 3) & (r < 10), 2], 10)
    return int(((cls == KEPT) & (r < 25) & (p[:, 2] - road < 0.25)).sum())


def test_kitti_sweeps_keep_their_objects_and_lose_their_ground(kitti):
    counts = []
    for i, p in enumerate(kitti):
        cls = preprocess_classes(p)
        n = np.bincount(cls, minlength=4)
        counts.append(n)
        in_range = len(p) - n[CROPPED]
        assert n[GROUND] > 0.4 * in_range, (i, n)  # the road is ground (frames 1-8 had ~1 %)
        assert 20 <= n[OUTLIER] <= 400, (i, n)     # the multipath returns, counted
        assert _low_kept(p, cls) < 1500, i          # no ground ring left in (31k before)
    kept = np.array([c[KEPT] for c in counts])
    for i in range(len(kept)):  # no frame keeps less than half the non-ground points of its neighbours
        for j in (i - 1, i + 1):
            if 0 <= j < len(kept):
                assert kept[i] >= 0.5 * kept[j], (i, kept)


def test_kitti_op_equals_the_numpy_reference(kitti):
    from floxels_ext.lidar.preprocess.masks_torch import preprocess_classes_torch

    for i in (0, 6, 12):
        a = preprocess_classes_numpy(kitti[i])
        np.testing.assert_array_equal(preprocess_classes(kitti[i]), a)
        np.testing.assert_array_equal(preprocess_classes_torch(kitti[i], Preprocess(), "cpu"), a)


def test_av2_ground_against_the_label():
    d = np.load(shared_path(*AV2))
    p, label = d["pc0"], d["is_ground0"].astype(bool)
    cls = preprocess_classes(p)
    sel = cls != CROPPED  # the range crop (and the height crop: nothing there is ground)
    pred = cls == GROUND
    tp = (pred & label & sel).sum()
    assert tp / (pred & sel).sum() >= 0.95 and tp / (label & sel).sum() >= 0.95
    # the same removal on pc1 (no label): a ground share like pc0's
    c1 = preprocess_classes(d["pc1"])
    share = lambda c: (c == GROUND).sum() / (c != CROPPED).sum()  # noqa: E731
    assert abs(share(c1) - share(cls)) < 0.03
