"""``run_summary.json``'s ``engines_start`` (``lidar/dataset/engine_start.JoinClock``): each
engine's first frame, when the last one joined, and the rate of the frames after that."""

from floxels_ext.lidar.dataset import engine_start
from floxels_ext.lidar.dataset.engine_start import JoinClock


def _clock(monkeypatch, n: int):
    now = [1000.0]
    monkeypatch.setattr(engine_start.time, "time", lambda: now[0])
    return JoinClock(n), now


def test_all_joined_and_the_rate_after(monkeypatch):
    c, now = _clock(monkeypatch, 3)
    for t, e in [(0.5, 0), (1.0, 0), (1.5, 1), (2.0, 0), (3.0, 2), (3.5, 1), (4.0, 2), (5.0, 0)]:
        now[0] = 1000.0 + t
        c.frame(e, ok=True)
    s = c.summary()
    assert s["run_started_at"] == 1000.0
    assert s["first_frame_s"] == {"0": 0.5, "1": 1.5, "2": 3.0}
    assert s["all_joined_s"] == 3.0 and s["last_frame_s"] == 5.0
    assert s["frames_per_s_after_join"] == 1.5  # 3 frames after the join (at 3.5, 4.0, 5.0) in 2 s


def test_an_engine_that_never_wrote_leaves_no_steady_rate(monkeypatch):
    c, now = _clock(monkeypatch, 2)
    for t in (1.0, 2.0, 3.0):
        now[0] = 1000.0 + t
        c.frame(0, ok=True)
    s = c.summary()
    assert s["first_frame_s"] == {"0": 1.0} and s["all_joined_s"] is None
    assert s["frames_per_s_after_join"] is None and s["last_frame_s"] == 3.0


def test_failed_frames_join_but_are_not_counted(monkeypatch):
    c, now = _clock(monkeypatch, 2)
    for t, e, ok in [(1.0, 0, True), (2.0, 1, False), (3.0, 0, True), (4.0, 1, True), (4.5, 0, False)]:
        now[0] = 1000.0 + t
        c.frame(e, ok)
    s = c.summary()
    assert s["all_joined_s"] == 2.0 and s["last_frame_s"] == 4.0  # the failed frame at 4.5 wrote nothing
    assert s["frames_per_s_after_join"] == 1.0  # 2 written after the join, in 2 s


def test_nothing_after_the_join(monkeypatch):
    c, now = _clock(monkeypatch, 2)
    for t, e in [(1.0, 0), (2.0, 1)]:
        now[0] = 1000.0 + t
        c.frame(e, ok=True)
    assert c.summary()["frames_per_s_after_join"] is None
