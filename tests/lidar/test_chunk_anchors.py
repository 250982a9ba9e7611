"""A frame's flow does not depend on how the run's frames are cut: each chunk is re-centred near
a frame fixed by its block of ``--chunk`` frames (``layout.plan_chunks``), not by the task or the
resumed run it belongs to. Before, a resumed run (or a task cut inside a chunk, as a Ray job's
tail halves are) re-centred its first chunk on its own first frame: float32 coordinates rounded
otherwise, the flow up to 2 cm off (a 32-beam simulated sequence, 20 iterations), and a Ray job's bytes depended on its timing.

The sequence moves 6 m a frame, so that frames of one chunk snap to different anchors."""

import numpy as np
import pytest

from floxels_ext import cli
from floxels_ext.lidar.dataset.layout import block_start, plan_chunks
from floxels_ext.lidar.io.outputs import read_flow_output
from moving_seq import moving_kitti_sequence  # noqa: E402

N_FRAMES = 9
FLAGS = ["--device", "cpu", "--max-iters", "4", "--scans", "3", "-q"]


def test_chunks_are_blocks_counted_from_the_selection():
    assert [len(c) for c in plan_chunks(list(range(150)), None)] == [128, 22]
    assert plan_chunks([5, 6, 7, 9, 12, 13], 4) == [[5, 6, 7], [9], [12, 13]]
    assert plan_chunks([5, 6, 7, 9, 12, 13], 4, origin=1) == [[5, 6, 7], [9, 12], [13]]
    assert plan_chunks([], 4) == []
    assert [block_start(i, 4, 1) for i in (1, 4, 5, 8, 9)] == [1, 1, 5, 5, 9]
    assert block_start(200, None) == 128


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    return moving_kitti_sequence(tmp_path_factory.mktemp("anchors"), N_FRAMES)


def _run(seq, out, *extra):
    velo, poses = seq
    assert cli.main(["run", str(velo), "--poses", str(poses), "--out", str(out), *FLAGS, *extra]) == 0


def _same_bytes(a, b, names):
    for n in names:
        x, y = read_flow_output(a / f"{n}.npz"), read_flow_output(b / f"{n}.npz")
        assert np.array_equal(x["flow"], y["flow"]), n
        assert np.array_equal(x["dynamic"], y["dynamic"]), n


def test_resumed_run_equals_the_whole_run(seq, tmp_path):
    """Frames 5.. redone after an interruption: their chunk (block 0..8 of --chunk 9) is still
    anchored at frame 0, as in the run that did them all."""
    whole, resumed = tmp_path / "whole", tmp_path / "resumed"
    _run(seq, whole, "--chunk", "9")
    _run(seq, resumed, "--chunk", "9", "--frames", "0:5")
    _run(seq, resumed, "--chunk", "9")  # frames 0-4 written: 5-8 left to do
    _same_bytes(whole, resumed, [f"{i:06d}" for i in range(N_FRAMES)])
