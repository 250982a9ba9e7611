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


_NPY_MAGIC = b"\x93NUMPY"
_ZIP_MAGIC = b"PK"


def _check_kind(path, want: str) -> None:
    """A ValueError naming what the file is when it is not the ``want`` kind ("npy" or "npz").
    Why: ``np.load`` takes any file that is neither as a pickle and, with pickles refused,
    says "This file contains pickled (object) data ... load it unsafely using allow_pickle="
    for random bytes, a text file or an HTML error page saved under the name, and raises
    EOFError (which callers catching ValueError miss) for an empty file."""
    if not isinstance(path, (str, os.PathLike)):
        return  # a file object: np.load judges it
    with open(path, "rb") as f:
        head = f.read(len(_NPY_MAGIC))
    if want == "npy" and head.startswith(_NPY_MAGIC) or want == "npz" and head.startswith(_ZIP_MAGIC):
        return
    if not head:
        raise ValueError("empty file (0 bytes)")
    if head.startswith(_NPY_MAGIC):
        raise ValueError("this is a .npy array, not a .npz archive")
    if head.startswith(_ZIP_MAGIC):
        raise ValueError("this is a .npz (zip) archive, not a .npy array")
    raise ValueError(f"not a .{want} file (it starts with {head!r}, not the "
                     + ("NumPy .npy header" if want == "npy" else ".npz (zip) signature") + ")")


@contextmanager
def open_npz(path: str | os.PathLike) -> Iterator[np.lib.npyio.NpzFile]:
    """``np.load(path, allow_pickle=False)`` of an ``.npz``, the lock held for the whole block
    (each array's header is parsed when the array is read). A file that is no zip archive
    (empty, another format) is a ValueError saying so."""
    _check_kind(path, "npz")
    with _LOCK, np.load(path, allow_pickle=False) as z:
        yield z


def load_npy(path: str | os.PathLike) -> np.ndarray:
    """``np.load(path, allow_pickle=False)`` of an ``.npy``, under the lock. A file without the
    .npy header (empty, a .npz, another format) is a ValueError saying so."""
    _check_kind(path, "npy")
    with _LOCK:
        return np.load(path, allow_pickle=False)
