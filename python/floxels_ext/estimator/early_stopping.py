"""Early stopping as in the paper (patience / min-delta) plus lowest-loss tracking."""

from __future__ import annotations


class EarlyStopping:
    """Stops after ``patience`` iterations without an improvement of at least ``min_delta``
    over the best loss so far; separately remembers the lowest loss seen (``is_best``), whose
    flow is the result."""

    def __init__(self, patience: int, min_delta: float) -> None:
        self.patience, self.min_delta = patience, min_delta
        self.ref = float("inf")      # best loss that counted as an improvement
        self.stale = 0
        self.best = float("inf")     # lowest loss seen
        self.best_iter = -1

    def update(self, loss: float, it: int) -> tuple[bool, bool]:
        """Record iteration ``it``'s loss; returns (is_new_lowest, should_stop)."""
        is_best = loss < self.best
        if is_best:
            self.best, self.best_iter = loss, it
        if loss < self.ref - self.min_delta:
            self.ref, self.stale = loss, 0
        else:
            self.stale += 1
        return is_best, self.stale >= self.patience
