"""Arrow columns (Argoverse 2 ``.feather`` sweeps and poses) as numpy arrays, without pyarrow's
pandas converter where the values are plain numbers.

``Array.to_numpy`` / ``ChunkedArray.to_numpy`` go through pyarrow's pandas converter, which
imports pandas on its first use: ~0.2 s with the GIL held, in the first AV2 sequence of every
``floxels run`` engine process (the fork server that starts them has no pandas), and a
ChunkedArray's conversion concatenates its chunks on the way (~0.3 ms a 216k-row column against
0.03 ms here). Integer and floating columns without nulls are read from their data buffer
(``np.frombuffer``): the same dtype and values as ``to_numpy(zero_copy_only=False)``. Anything
else (nulls, booleans, strings, timestamps...) still goes through ``to_numpy``. A sweep's x, y, z
come as float32 rows from Arrow's own calls (:func:`one_chunk`, :func:`xyz_rows`): few
calls, each without the GIL (bench/RESULTS.md, "reader path" section: copying chunk by chunk
from Python cost less CPU but gave the GIL up and took it back twice as often).
"""

from __future__ import annotations

import functools

import numpy as np

__all__ = ["column_values", "chunk_values", "one_chunk", "xyz_rows"]


def _plain(arr) -> np.dtype | None:
    """The numpy dtype of ``arr``'s values when its data buffer holds them as they are (an
    integer or floating type, no nulls), else None."""
    t = arr.type
    if arr.null_count or t.id not in _plain_ids():
        return None
    return np.dtype(t.to_pandas_dtype())


def chunk_values(chunk) -> np.ndarray:
    """One ``pyarrow.Array`` as ``chunk.to_numpy(zero_copy_only=False)`` gives it (a read-only
    view of the Arrow buffer for plain numbers, as ``to_numpy`` gives those too)."""
    dt = _plain(chunk)
    if dt is None:
        return chunk.to_numpy(zero_copy_only=False)
    if len(chunk) == 0:
        return np.empty(0, dt)
    return np.frombuffer(chunk.buffers()[1], dt, count=len(chunk), offset=chunk.offset * dt.itemsize)


def column_values(col) -> np.ndarray:
    """A ``pyarrow.ChunkedArray`` as ``col.to_numpy(zero_copy_only=False)`` gives it: one chunk
    as :func:`chunk_values`, several concatenated (a new array)."""
    chunks = col.chunks
    if not chunks and col.type.id in _plain_ids():
        return np.empty(0, np.dtype(col.type.to_pandas_dtype()))
    if chunks and all(_plain(c) is not None for c in chunks):
        return chunk_values(chunks[0]) if len(chunks) == 1 else np.concatenate([chunk_values(c) for c in chunks])
    return col.to_numpy(zero_copy_only=False)


def one_chunk(table):
    """``table`` with each column in one chunk (``Table.combine_chunks``: one Arrow call without
    the GIL, instead of a concatenation per column from Python) where every column is a plain
    number type; else ``table`` as it is (the columns are then converted one by one)."""
    ids = _plain_ids()
    if all(c.num_chunks <= 1 for c in table.columns) or not all(f.type.id in ids for f in table.schema):
        return table
    return table.combine_chunks()


def xyz_rows(table) -> np.ndarray | None:
    """Columns x, y, z of ``table`` as (N, 3) float32 rows, in two Arrow calls that run without
    the GIL (the chunks combined, then ``RecordBatch.to_tensor``, row-major; then numpy's cast,
    if any), where the three share one integer or floating type without nulls; None otherwise
    (or with a pyarrow without ``to_tensor``): the caller fills the rows chunk by chunk. The
    same values as numpy's assignment of each column into float32 rows (one cast per value)."""
    cols = [table.column(c) for c in "xyz"]
    t = cols[0].type
    if table.num_rows == 0 or t.id not in _plain_ids() or any(c.type != t or c.null_count for c in cols):
        return None
    batches = table.select(["x", "y", "z"]).combine_chunks().to_batches()
    if len(batches) != 1 or not hasattr(batches[0], "to_tensor"):
        return None
    try:
        rows = batches[0].to_tensor(row_major=True).to_numpy()
    except (TypeError, NotImplementedError, ValueError):  # (pyarrow's errors derive from these)
        return None
    if rows.dtype != np.float32:
        return rows.astype(np.float32)
    return rows if rows.flags.writeable and rows.flags.c_contiguous else np.array(rows, np.float32)


@functools.cache
def _plain_ids() -> frozenset:
    """The Arrow type ids whose data buffer numpy reads as it is (pyarrow imported on first use)."""
    import pyarrow as pa

    return frozenset(t.id for t in (pa.int8(), pa.int16(), pa.int32(), pa.int64(), pa.uint8(), pa.uint16(),
                                    pa.uint32(), pa.uint64(), pa.float16(), pa.float32(), pa.float64()))
