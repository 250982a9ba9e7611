"""The CPU thread default of the commands (issue 30, item 6; floxels_ext.cpu_threads): as many
threads as the load average leaves cores free, at least 1; OMP_NUM_THREADS wins."""

import torch

from floxels_ext.cpu_threads import apply_cpu_threads, choose_cpu_threads


def test_threads_follow_the_free_cores():
    assert choose_cpu_threads(2, 0.0) == 2      # idle 2-core machine: one thread per core
    assert choose_cpu_threads(2, 1.0) == 1      # one core busy elsewhere
    assert choose_cpu_threads(2, 13.0) == 1     # the contended case measured (load 12-14): 1 thread
    assert choose_cpu_threads(16, 3.2) == 13
    assert choose_cpu_threads(16, 0.0) == 16


def test_omp_num_threads_wins(monkeypatch):
    before = torch.get_num_threads()
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert apply_cpu_threads() is None and torch.get_num_threads() == before
    monkeypatch.delenv("OMP_NUM_THREADS")
    said = []
    try:
        n = apply_cpu_threads(said.append)
        assert n == torch.get_num_threads() and said and said[0].startswith(f"CPU threads: {n} (load average")
    finally:
        torch.set_num_threads(before)
