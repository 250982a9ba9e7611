"""The host reads after the optimiser merged over a group's problems (estimator/host_reads.py):
the same results as one problem at a time, one read per round for all of them."""

import numpy as np
import pytest
import torch

from floxels_ext import FloxelsConfig, estimate_sequence
from floxels_ext.estimator import host_reads, post
from floxels_ext.estimator.host_reads import rows_where, run_one, run_steps
from test_accurate_preset import highway  # noqa: F401  (5 simulated highway frames, sensors, ground)


@pytest.mark.parametrize("p", [0.0, 0.3, 1.0])
def test_rows_where_is_boolean_indexing(p):
    mask = torch.rand(1000, generator=torch.Generator().manual_seed(1)) < p
    x = torch.arange(1000) * 7
    assert torch.equal(x[rows_where(mask, int(mask.sum()))], x[mask])


def _steps(values):
    """A problem that asks for the sum of each of ``values`` in turn (a round each)."""
    total = 0
    for v in values:
        (got,) = yield [torch.tensor(v).sum()]
        total += got
    return total


def test_run_steps_reads_every_problem_once_per_round(monkeypatch):
    problems = [[1, 2, 3], [], [4], [5, 6]]
    reads = []
    real = host_reads._read
    monkeypatch.setattr(host_reads, "_read", lambda counts: reads.append(len(counts)) or real(counts))
    assert run_steps([_steps(v) for v in problems]) == [6, 0, 4, 11]
    assert reads == [3, 2, 1]  # rounds: 3 problems ask, then 2, then 1
    reads.clear()
    assert [run_one(_steps(v)) for v in problems] == [6, 0, 4, 11]


def test_accurate_sequence_in_one_group_gives_the_same_bits(highway, monkeypatch):
    """Every frame's flow and evidence the same bits whether its steps after the optimiser run
    alone or in lockstep with the other frames of its group (their host reads merged)."""
    scans, sensors, ground, _, _ = highway
    cfg = FloxelsConfig.preset("accurate", max_iters=60)
    groups = []
    real = post.run_steps
    monkeypatch.setattr(post, "run_steps", lambda steps: groups.append(len(steps)) or real(steps))

    def run(batch):
        got = {}
        estimate_sequence(scans, cfg, device="cpu", batch_size=batch, sensor_origins=sensors, ground_points=ground,
                          callback=lambda f, r: got.__setitem__(f, r))
        return got

    alone = run(1)
    reads = []
    real_read = host_reads._read
    monkeypatch.setattr(host_reads, "_read", lambda counts: reads.append(len(counts)) or real_read(counts))
    together = run(len(scans))
    assert groups == [1] * len(scans) + [len(scans)]
    # three rounds for the whole group: the refinement's read (a count a frame), the spreading's
    # two (two counts, then one, a frame with an accepted motion)
    assert len(reads) == 3 and reads[0] == len(scans) and reads[1] >= 4, reads
    for f in range(len(scans)):
        for field in ("flow", "evidence", "explained"):
            a, b = np.asarray(getattr(alone[f], field)), np.asarray(getattr(together[f], field))
            assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), (f, field)
