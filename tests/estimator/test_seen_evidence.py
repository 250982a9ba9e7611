"""The evidence test judged on what the support scans saw (issue 47: ``evidence_seen_mean``,
``evidence_keep_unseen``, in the ``accurate`` preset). A car approaching the ego from behind, at
the first frame of a sequence: every later scan shows the car itself in front of the car's old
place, so no support scan saw the place, the test had no evidence and zeroed a correct flow
(``paper`` keeps it); now kept where a rigid motion explains the scans clearly better than zero
flow (estimator/post.py). Also the formula of :func:`seen_evidence` on hand-made residuals."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from floxels_ext.estimator import FloxelsConfig, estimate_sequence
from floxels_ext.estimator.evidence import seen_evidence, sensor_velocity
from floxels_ext.evaluation.protocol import protocol_mask
from floxels_ext.evaluation.sim import Scene, Track, simulate_sequence
from floxels_ext.evaluation.sim.scene import BACKGROUND, CAR, PEDESTRIAN


def test_seen_evidence_rescues_partly_seen_groups_unless_they_follow_the_sensor():
    # groups (runs of labels): 0 (two points seen by scan 1 only), 1 (seen by none), 2 (all)
    labels = torch.tensor([0, 0, 1, 1, 2])
    cells = torch.zeros(5, dtype=torch.int64)
    observed = torch.tensor([0b10, 0b10, 0, 0, 0b11], dtype=torch.int32)
    w = [0.8, 0.2]  # normalised weights of scans 0 and 1
    rz = torch.tensor([0.012, 0.012, 0.0, 0.0, 0.1])  # the op's group means (normalised over all scans)
    rf = torch.tensor([0.001, 0.001, 0.0, 0.0, 0.09])
    score, explained = rz - rf, (rz - rf) > torch.clamp(rz * 0.05, min=0.02)
    kw = dict(margin=0.02, ratio=0.05)
    # group 0 judged on scan 1 alone: residuals / 0.2 -> gain 0.055 against the margin of that scan's
    # mean, 0.02 * sqrt(0.2^2 / (0.8^2 + 0.2^2)) / 0.2 = 0.0243 (as given: 0.011 < 0.02, failed)
    ev = seen_evidence(score, explained, rf, rz, labels, cells, observed, w, seen_mean=True, keep_unseen=True, **kw)
    assert ev.explained.tolist() == [True, True, True, True, False]
    assert ev.hidden.tolist() == [False, False, True, True, False]  # no occluded bits given: every unseen group
    assert torch.equal(ev.score, score) and torch.equal(ev.residual_zero, rz)
    # ... unless its flow points along the sensors' velocity (structure whose visible part follows
    # the sensor, at its speed or a part of it)
    flow = torch.tensor([[2.5, 0.0, 0.0]] * 5)
    for v, rescued in (([2.4, 0.1, 0.0], False), ([4.6, 0.3, 0.0], False), ([0.0, 0.5, 0.0], True),
                       ([-1.0, 0.0, 0.0], True), ([0.01, 0.0, 0.0], True)):
        ev = seen_evidence(score, explained, rf, rz, labels, cells, observed, w, seen_mean=True, keep_unseen=False,
                           flow=flow, sensor_velocity=torch.tensor(v), **kw)
        assert ev.explained[:2].tolist() == [rescued] * 2 and ev.hidden is None
    # a gain that clears the whole window's margin once divided by the share, not the margin of the
    # mean over the scans that saw it (0.0045 / 0.2 = 0.0225: 0.02 < 0.0225 < 0.0243; issue 47's
    # static structure at the sequences' ends)
    weak = torch.tensor([0.0055, 0.0055, 0.0, 0.0, 0.1])
    ev = seen_evidence(weak - rf, (weak - rf) > 0.02, rf, weak, labels, cells, observed, w, seen_mean=True,
                       keep_unseen=False, **kw)
    assert ev.explained.tolist() == [False, False, False, False, False]
    # ... with keep_unseen it awaits the rigid refinement's confirmation, as a hidden group does
    ev = seen_evidence(weak - rf, (weak - rf) > 0.02, rf, weak, labels, cells, observed, w, seen_mean=True,
                       keep_unseen=True, **kw)
    assert ev.hidden.tolist() == [True, True, True, True, False] and ev.explained.tolist() == ev.hidden.tolist()
    # hidden needs most points behind a nearer return where the occluded bits are given
    occ = torch.tensor([0, 0, 0b01, 0, 0], dtype=torch.int32)
    ev = seen_evidence(score, explained, rf, rz, labels, cells, observed, w, seen_mean=False, keep_unseen=True,
                       occluded=occ, **kw)
    assert ev.hidden.tolist() == [False, False, True, True, False]  # 1 of 2 points: half
    occ = torch.tensor([0, 0, 0, 0, 0], dtype=torch.int32)
    ev = seen_evidence(score, explained, rf, rz, labels, cells, observed, w, seen_mean=False, keep_unseen=True,
                       occluded=occ, **kw)
    assert not ev.hidden.any() and ev.explained.tolist() == explained.tolist()


def test_sensor_velocity_is_the_least_squares_line():
    s = [torch.tensor([2.0 * t, 1.0, 0.5]) for t in (-2, -1, 1, 2)]
    assert torch.allclose(sensor_velocity(s, [-2, -1, 1, 2]), torch.tensor([2.0, 0.0, 0.0], dtype=torch.float64))
    assert sensor_velocity([s[0], None], [-2, -1]) is None
    assert torch.allclose(sensor_velocity([s[0], None, s[3]], [-2, -1, 2]), torch.tensor([2.0, 0, 0], dtype=torch.float64))


def _cropped(seq, frame: int, max_range: float = 30.0):
    """A simulated sequence as the API takes it: protocol-cropped scans, poses, removed ground;
    and frame ``frame`` with its kept rows."""
    scans, grounds = [], []
    for fr in seq.frames:
        scans.append(fr.points[protocol_mask(fr.points, fr.pose[:3, 3], ground=fr.ground, max_range=max_range)]
                     .astype(np.float32))
        grounds.append(fr.points[fr.ground.astype(bool) & protocol_mask(fr.points, fr.pose[:3, 3], max_range=max_range)]
                       .astype(np.float32))
    fr = seq.frames[frame]
    keep = protocol_mask(fr.points, fr.pose[:3, 3], ground=fr.ground, max_range=max_range)
    return scans, np.stack([f.pose for f in seq.frames]), grounds, fr, keep


def _behind(n=6):
    """A 32-beam sequence: the ego at 0.86 m/frame between two walls, a car 16 m behind it at
    0.92 m/frame; protocol-cropped scans, poses, removed ground, car mask and flow of frame 0."""
    s = Scene("behind", Track(0.0, 0.0, 0.0, 8.6), horizon=(n + 1) * 0.1)
    s.add((4.5, 1.8, 1.5), CAR, -16.0, 0.0, 0.0, 9.2)
    for y in (-7.0, 7.0):
        s.add((200, 0.5, 3.0), BACKGROUND, 0.0, y)
    seq = simulate_sequence(s, num_frames=n, seed=0, beams=32, azimuth_steps=1024)
    scans, poses, grounds, fr, keep = _cropped(seq, 0)
    return scans, poses, grounds, fr.instance[keep] == 0, fr.flow[keep]


@pytest.fixture(scope="module")
def behind():
    return _behind()


@pytest.mark.parametrize("keep_unseen, kept", [(False, False), (True, True)])
def test_a_car_from_behind_keeps_its_motion_at_the_first_frame(behind, keep_unseen, kept):
    scans, poses, grounds, car, truth = behind
    cfg = FloxelsConfig.preset("accurate", num_scans=6, evidence_seen_mean=True, evidence_keep_unseen=keep_unseen)
    flow = estimate_sequence(scans, cfg, frames=[0], poses=poses, ground_points=grounds)[0]
    assert car.sum() > 50
    err = np.linalg.norm(flow[car] - truth[car], axis=1).mean()
    if kept:  # (kept where a rigid motion fits the car's clusters; a few unclustered points are zeroed)
        assert np.mean(np.linalg.norm(flow[car] - truth[car], axis=1) < 0.1) > 0.9
        assert np.linalg.norm(flow[~car], axis=1).mean() < 0.01  # the walls stay put
    else:
        assert err > 0.8  # the failure: zeroed (no scan saw the car's old place)


def _parked_row(n=5):
    """A 32-beam sequence: the ego at 1 m/frame past a row of parked cars 5 m beside it (4.8 m
    apart), a pedestrian crossing ahead, walls; protocol-cropped scans, poses, removed ground and
    the last frame's flow (its window one-sided: the past scans only)."""
    s = Scene("row", Track(0.0, 0.0, 0.0, 10.0), horizon=(n + 1) * 0.1)
    for k in range(-3, 6):
        s.add((4.5, 1.8, 1.5), CAR, 4.8 * k + 2.0, 5.0, 0.0, 0.0)
    s.add((0.5, 0.5, 1.7), PEDESTRIAN, 8.0, -6.0, 1.5708, 1.2)
    for y in (-9.0, 9.0):
        s.add((200, 0.5, 3.0), BACKGROUND, 0.0, y)
    seq = simulate_sequence(s, num_frames=n, seed=0, beams=32, azimuth_steps=1024)
    scans, poses, grounds, fr, keep = _cropped(seq, -1)
    return scans, poses, grounds, fr.flow[keep]


def test_parked_cars_at_a_sequence_end_are_not_rescued_on_sampling_level_gains():
    # issue 47: the last frame's window sees a parked car beside the ego only from behind, each point
    # by some of the past scans (between the 32 beams' rings, around the car's corners); a flow of a
    # few cm/frame removes a sampling-level part of its residual. Judged on the share of the window
    # that saw it with the whole window's margin, such structure passed (126 static points moved
    # against 82 without the rescue); with the margin of a mean over that share it keeps what the
    # all-scans test gives it, and the crossing pedestrian keeps its motion
    scans, poses, grounds, truth = _parked_row()
    f = len(scans) - 1
    dyn = np.linalg.norm(truth, axis=1) > 0.05
    cfg = FloxelsConfig.preset("accurate", num_scans=5)
    moved = {}
    for seen_mean in (True, False):
        flow = estimate_sequence(scans, cfg.replace(evidence_seen_mean=seen_mean), frames=[f], poses=poses,
                                 ground_points=grounds)[0]
        moved[seen_mean] = int((np.linalg.norm(flow[~dyn], axis=1) > 0.05).sum())
        assert dyn.sum() > 100 and np.linalg.norm(flow[dyn] - truth[dyn], axis=1).mean() < 0.05
    assert moved[True] <= moved[False] + 5, moved
