"""``.npy`` / ``.npz`` reading behind one process-wide lock.

Why: numpy parses each array's header with ``ast.literal_eval``, and CPython 3.11 (the version
CI and the README's set-up use) can fail that parse when several threads run it at once
(CPython gh-106905: ``SystemError: AST constructor recursion depth mismatch``). ``floxels run``
reads frames on several threads, and a frame failed that way now and then (the test suite saw it
in ``tests/lidar``). Every read of ours goes through here, so no two of them parse at once; what
the lock costs is that two threads never decompress ``.npz`` files at the same time.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np

__all__ = ["open_npz", "load_npy"]

_LOCK = threading.RLock()  # re-entrant: a read inside another read cannot deadlock


@contextmanager
def open_npz(path: str | os.PathLike) -> Iterator[np.lib.npyio.NpzFile]:
    """``np.load(path, allow_pickle=False)`` of an ``.npz``, the lock held for the whole block
    (each array's header is parsed when the array is read)."""
    with _LOCK, np.load(path, allow_pickle=False) as z:
        yield z


def load_npy(path: str | os.PathLike) -> np.ndarray:
    """``np.load(path, allow_pickle=False)`` of an ``.npy``, under the lock."""
    with _LOCK:
        return np.load(path, allow_pickle=False)
