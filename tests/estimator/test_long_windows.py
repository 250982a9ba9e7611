"""Long windows in the ``accurate`` preset (issue 47). ``reg_scale="weights"``: the regularisers
scaled like the data term (the window's summed time weights), not by the count of support scans;
by the count, an 11-scan window over a parking lot with one slow pedestrian never improved on
zero flow and returned no flow at all. ``max_offset``: the windows at a sequence's ends,
shifted inwards, keep no scan farther than this from the target (a cyclist at the last frame of
11: its 10 past scans left the optimiser at 0.09 m/frame for 0.56)."""

from __future__ import annotations

import numpy as np
import pytest

from floxels_ext.estimator import FloxelsConfig, estimate_flow, estimate_sequence, window_for


def test_weights_scale_matches_the_paper_at_five_scans_and_the_data_term_beyond():
    c = FloxelsConfig(reg_scale="weights")
    assert c.regulariser_scale(4, [-2.0, -1.0, 1.0, 2.0]) == pytest.approx(4.0)
    w11 = 2 * sum(1 / t ** 2 for t in range(1, 6))
    assert c.regulariser_scale(10, [float(t) for t in range(-5, 6) if t]) == pytest.approx(4.0 * w11 / 2.5)
    assert c.regulariser_scale(4, [1.0, 2.0, 3.0, 4.0]) == pytest.approx(4.0 * (1 + 1 / 4 + 1 / 9 + 1 / 16) / 2.5)
    assert FloxelsConfig().regulariser_scale(10) == 10.0  # the paper's reading unchanged
    with pytest.raises(ValueError, match="offsets"):
        c.regulariser_scale(4)
    with pytest.raises(ValueError, match="reg_scale"):
        FloxelsConfig(reg_scale="count")


def _lot(n_static=4000, n_ped=60, v=0.12, frames=11, seed=0):
    """Parked cars (box surfaces) on a 20 x 20 m lot and one pedestrian walking v m/frame."""
    g = np.random.default_rng(seed)
    centres = g.uniform(-9, 9, (30, 2))
    half = np.array([2.2, 0.9, 0.75])
    scans = []
    for i in range(frames):
        parts = []
        for c in centres:
            u = g.uniform(-1, 1, (n_static // 30, 3)) * half
            face = g.integers(0, 3, len(u))
            u[np.arange(len(u)), face] = np.sign(u[np.arange(len(u)), face]) * half[face]
            parts.append(u + [c[0], c[1], 0.75])
        u = g.uniform(-1, 1, (n_ped, 3)) * [0.3, 0.3, 0.9]
        face = g.integers(0, 2, n_ped)
        u[np.arange(n_ped), face] = np.sign(u[np.arange(n_ped), face]) * 0.3
        parts.append(u + [2.0 + v * i, 0.5, 0.9])
        p = np.concatenate(parts)
        scans.append((p + g.normal(0, 0.02, p.shape)).astype(np.float32))
    return scans


def test_weights_scale_keeps_a_slow_pedestrian_in_an_eleven_scan_window():
    scans = _lot()
    ped = slice(len(scans[5]) - 60, None)
    by_count = estimate_sequence(scans, FloxelsConfig(num_scans=11, max_iters=300), frames=[5])[0]
    by_weight = estimate_sequence(scans, FloxelsConfig(num_scans=11, max_iters=300, reg_scale="weights"), frames=[5])[0]
    assert np.abs(by_count).max() == 0.0  # the failure: zero flow everywhere
    assert abs(np.linalg.norm(by_weight[ped], axis=1).mean() - 0.12) < 0.03


def test_max_offset_cuts_the_windows_at_the_ends():
    assert window_for(0, 40, 11, 5) == (0, 6)
    assert window_for(39, 40, 11, 5) == (34, 40)
    assert window_for(20, 40, 11, 5) == (15, 26)  # the centred window is unchanged
    assert window_for(2, 40, 11, 5) == (0, 8)
    assert window_for(0, 40, 11) == (0, 11)
    assert window_for(0, 3, 11, 5) == (0, 3)
    with pytest.raises(ValueError, match="max_offset"):
        FloxelsConfig(max_offset=-1)


def test_max_offset_sequence_is_the_shorter_window():
    g = np.random.default_rng(3)
    base = g.uniform(-5, 5, (800, 3)).astype(np.float32)
    scans = [base + np.float32(0.3) * i * np.array([1, 0, 0], np.float32) for i in range(9)]
    cfg = FloxelsConfig(num_scans=7, max_offset=2, max_iters=20)
    seq = estimate_sequence(scans, cfg, frames=[0, 8])
    assert np.array_equal(seq[0], estimate_flow(scans[0:3], 0, cfg))
    assert np.array_equal(seq[1], estimate_flow(scans[6:9], 2, cfg))
