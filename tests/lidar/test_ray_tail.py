"""The Ray driver's tail (``ray_tail``): each worker's share of the work left, and where a task
handed out near the end is cut (``tasks.halve_task(first=...)``)."""

import pytest

from floxels_ext.lidar.dataset.ray_tail import CUT_MARGIN, RATE_FRAMES, SHARE_QUEUE, TailShare, cut_here, first_part
from floxels_ext.lidar.dataset.tasks import SequenceSpec, Task, halve_task


def _task(a, b, selection=None):
    spec = SequenceSpec(None, None, None, None)
    names = [f"{i:06d}" for i in range(a, b)]
    return Task(spec, None, a, b, names, frame_paths=names, selection=selection, todo=list(names))


def test_rates_start_at_the_first_report_and_need_enough_frames():
    t = TailShare()
    t.written("a", 5, 10.0)           # the first report starts the clock; its frames are not counted
    assert t.rate("a", 11.0) is None  # nothing after it yet
    t.written("a", RATE_FRAMES - 1, 11.0)
    assert t.rate("a", 11.0) is None
    t.written("a", 1, 11.0)
    assert t.rate("a", 12.0) == pytest.approx(RATE_FRAMES / 2.0)
    t.written("b", 0, 10.0)           # a report without frames starts nothing
    assert "b" not in t.since


def test_share_is_the_frames_a_worker_does_before_the_balanced_end():
    t = TailShare()
    for w, rate in (("fast", 60), ("slow", 30)):
        t.written(w, 1, 0.0)
        t.written(w, rate * 10, 10.0)
    # 90 frames/s in all; 120 queued + 60 + 0 held: 2 s left; fast does 120 in that time, holds 60
    assert t.share("fast", {"fast": 60, "slow": 0}, 120, 10.0) == pytest.approx(60.0)
    assert t.share("slow", {"fast": 60, "slow": 0}, 120, 10.0) == pytest.approx(60.0)
    # a worker that holds more than its share gets none (cut to the smallest part)
    assert t.share("fast", {"fast": 300, "slow": 0}, 30, 10.0) < 0
    # a worker without a rate counts at the others' mean; no rate at all: no share
    assert t.share("new", {"fast": 0, "slow": 0, "new": 0}, 135, 10.0) == pytest.approx(45.0)
    assert TailShare().share("a", {"a": 0, "b": 0}, 100, 1.0) is None
    assert t.share("gone", {"fast": 0}, 100, 10.0) is None  # not among the running workers


def test_cut_at_the_share_and_the_last_tasks_halved():
    assert cut_here(150, 200.0, 8, 8) is None                   # within its share: whole
    assert cut_here(150, 150 - CUT_MARGIN, 8, 8) is None        # by the margin: whole
    assert cut_here(150, 60.0, 20, 8) == 60.0                    # cut at the share, whatever the queue
    assert cut_here(150, -30.0, 20, 8) == 0.0                    # more held than its share: the smallest part
    # the last tasks (queue shorter than the workers): halved, or at the share if it comes first
    assert cut_here(150, 200.0, 7, 8) == 75.0
    assert cut_here(150, 100.0, 7, 8) == 75.0
    assert cut_here(150, 60.0, 7, 8) == 60.0
    assert cut_here(150, None, 7, 8) == 75.0                     # no rate: halved while the queue < workers
    assert cut_here(150, None, 8, 8) is None


def test_halve_task_cuts_near_the_frames_asked_for():
    a, b = halve_task(_task(0, 150), align=1, min_frames=16, first=60)
    assert (a.start, a.stop, b.start, b.stop) == (0, 60, 60, 150)
    assert a.names + b.names == _task(0, 150).names and a.todo + b.todo == _task(0, 150).todo
    a, b = halve_task(_task(0, 150), align=1, min_frames=16, first=0)    # at least min_frames
    assert (a.stop, b.start) == (16, 16)
    a, b = halve_task(_task(0, 150), align=1, min_frames=16, first=149)  # the rest too
    assert (a.stop, b.start) == (134, 134)
    a, b = halve_task(_task(10, 266, selection=(10, 266)), align=64, min_frames=16, first=100)
    assert a.stop == 138 and (a.stop - 10) % 64 == 0                     # the nearest allowed cut
    a, b = halve_task(_task(0, 150), align=1, min_frames=16)             # no first: the middle
    assert a.stop == 75


def test_first_part_works_out_shares_only_near_the_end():
    t = TailShare()
    for w in ("a", "b"):
        t.written(w, 1, 0.0)
        t.written(w, 500, 10.0)   # 50 frames/s each
    held = {"a": 0, "b": 100}
    # far from the end (SHARE_QUEUE tasks a worker queued): whole, even where a share would cut it
    # ("b" holds more than its share of 150 + 1,200 queued + 2,000 held)
    assert first_part(t, "b", 150, [150] * (SHARE_QUEUE * 2), {"a": 0, "b": 2000}, 10.0) is None
    assert first_part(t, "b", 150, [150] * (SHARE_QUEUE * 2 - 1), {"a": 0, "b": 2000}, 10.0) == 0.0
    # near it: 150 + 300 queued + 300 held = 750 frames, 7.5 s at 100 frames/s: each does 375
    held = {"a": 0, "b": 300}
    assert first_part(t, "a", 150, [150, 150], held, 10.0) is None
    assert first_part(t, "b", 150, [150, 150], held, 10.0) == pytest.approx(75.0)  # 375 - the 300 it holds
    assert first_part(t, "a", 150, [150], held, 10.0) == 75.0  # the last tasks: halved whatever the share
    # no rates yet: halved while the queue is shorter than the workers
    assert first_part(TailShare(), "a", 150, [150], held, 10.0) == 75.0
    assert first_part(TailShare(), "a", 150, [150, 150], held, 10.0) is None
