"""The Ray driver's tail cut (``tasks.halve_task``): a task is halved only where the planner could
have cut it (a multiple of ``--chunk`` from the selection's first frame, so every window and batch
stays the run's), each part at least the minimum, both with frames left to do."""

from pathlib import Path

from floxels_ext.lidar.dataset.tasks import SequenceSpec, Task, halve_task


def _task(start, stop, selection=None, todo=None):
    names = [f"{i:06d}" for i in range(start, stop)]
    return Task(SequenceSpec(Path("seq"), Path(".")), Path("out"), start, stop, names,
                todo=list(names) if todo is None else todo, frame_paths=[f"{n}.bin" for n in names],
                selection=selection or (0, stop))


def test_cut_at_the_chunk_multiple_nearest_the_middle():
    a, b = halve_task(_task(0, 150), align=64, min_frames=32)
    assert (a.start, a.stop, b.start, b.stop) == (0, 64, 64, 150)
    assert a.names == [f"{i:06d}" for i in range(64)] and b.frame_paths[0] == "000064.bin"
    assert a.todo == a.names and b.todo == b.names
    a, b = halve_task(_task(0, 512), align=64, min_frames=32)
    assert (a.stop, b.start) == (256, 256)


def test_cuts_counted_from_the_selection_start():
    a, b = halve_task(_task(10, 150, selection=(10, 150)), align=64, min_frames=32)
    assert (a.stop, b.start) == (74, 74)
    # a later task of that selection: its cuts are 10 + k * 64 too
    a, b = halve_task(_task(74, 266, selection=(10, 266)), align=64, min_frames=32)
    assert (a.stop, b.start) == (138, 138)  # 138 and 202 are as near the middle: the first


def test_no_cut_where_none_fits():
    assert halve_task(_task(64, 150), align=64, min_frames=32) is None   # 128 leaves 22 frames
    assert halve_task(_task(0, 40), align=1, min_frames=32) is None      # too short for two of 32
    assert halve_task(_task(0, 64), align=1, min_frames=32) is not None


def test_no_cut_that_leaves_a_part_with_nothing_to_do():
    t = _task(0, 150, todo=[f"{i:06d}" for i in range(64)])  # frames 64.. already written
    assert halve_task(t, align=64, min_frames=32) is None
    t = _task(0, 150, todo=[f"{i:06d}" for i in range(60, 70)])
    a, b = halve_task(t, align=64, min_frames=32)
    assert a.todo == [f"{i:06d}" for i in range(60, 64)] and b.todo == [f"{i:06d}" for i in range(64, 70)]
