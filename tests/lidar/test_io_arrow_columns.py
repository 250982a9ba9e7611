"""Arrow columns read from their buffers (``lidar/io/_arrow.py``): the same dtype and bytes as
pyarrow's ``to_numpy(zero_copy_only=False)``, and an AV2 log read without importing pandas."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pa = pytest.importorskip("pyarrow")

from floxels_ext.lidar.io._arrow import chunk_values, column_values  # noqa: E402


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    if a.dtype != b.dtype or a.shape != b.shape:
        return False
    return list(a) == list(b) if a.dtype == object else a.tobytes() == b.tobytes()


COLUMNS = {
    "float16": pa.chunked_array([np.array([1.5, -2, 3], np.float16), np.array([4], np.float16)]),
    "float32 sliced": pa.chunked_array([pa.array(np.arange(10, dtype=np.float32)).slice(3, 4),
                                        pa.array(np.arange(5, dtype=np.float32)).slice(1)]),
    "float64 nulls": pa.chunked_array([pa.array([1.0, None]), pa.array([3.0])]),
    "int32 nulls in one chunk": pa.chunked_array([pa.array([1, 2], pa.int32()), pa.array([None, 4], pa.int32())]),
    "uint8": pa.chunked_array([pa.array([1, 2], pa.uint8()), pa.array([255], pa.uint8())]),
    "int64 one chunk": pa.chunked_array([pa.array([5, 6, 7], pa.int64())]),
    "int64 no chunk": pa.chunked_array([], pa.int64()),
    "int64 an empty chunk": pa.chunked_array([pa.array([], pa.int64()), pa.array([1], pa.int64())]),
    "uint64 sliced": pa.chunked_array([pa.array(np.arange(6, dtype=np.uint64)).slice(2, 3)]),
    "bool": pa.chunked_array([pa.array([True, False]), pa.array([True])]),
    "string": pa.chunked_array([pa.array(["a", "b"]), pa.array([None], pa.string())]),
    "dictionary": pa.chunked_array([pa.array(["a", "b", "a"]).dictionary_encode()]),
}


@pytest.mark.parametrize("name", sorted(COLUMNS))
def test_column_values_as_to_numpy(name):
    col = COLUMNS[name]
    assert _same(column_values(col), col.to_numpy(zero_copy_only=False))
    for chunk in col.chunks:
        assert _same(chunk_values(chunk), chunk.to_numpy(zero_copy_only=False))


def test_av2_log_read_without_pandas(tmp_path):
    """An engine process's first AV2 sequence (sweeps and poses) used to import pandas through
    pyarrow's converter (~0.2-0.35 s holding the GIL)."""
    feather = pytest.importorskip("pyarrow.feather")
    lidar = tmp_path / "log" / "sensors" / "lidar"
    lidar.mkdir(parents=True)
    g = np.random.default_rng(0)
    for t in (100, 200):
        xyz = g.normal(0, 10, (50, 3)).astype(np.float16)
        feather.write_feather(pa.table({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2],
                                        "intensity": np.arange(50, dtype=np.uint8),
                                        "offset_ns": np.arange(50, dtype=np.int32)}), str(lidar / f"{t}.feather"))
    one = {"qw": [1.0, 1.0], "qx": [0.0, 0.0], "qy": [0.0, 0.0], "qz": [0.0, 0.0],
           "tx_m": [0.0, 1.0], "ty_m": [0.0, 0.0], "tz_m": [0.0, 0.0]}
    feather.write_feather(pa.table({"timestamp_ns": np.array([100, 200], np.int64), **one}),
                          str(tmp_path / "log" / "city_SE3_egovehicle.feather"))
    code = ("import sys; from floxels_ext.lidar.io.sources import discover_input; "
            f"s = discover_input({str(tmp_path / 'log')!r}); a = s.load(0); b = s.load(1); "
            "assert s.poses.shape == (2, 4, 4) and a.points.shape == (50, 3); "
            "print('pandas' in sys.modules)")
    python_dir = str(Path(__file__).resolve().parents[2] / "python")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                         env={"PYTHONPATH": python_dir, "PATH": "/usr/bin:/bin"})
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"


@pytest.mark.parametrize("dtype", [np.float16, np.float32, np.float64, np.int32, np.uint8, np.int64])
def test_feather_rows_of_one_type_as_assigned(tmp_path, dtype):
    """x, y, z of one type without nulls (AV2: float16) come as rows from Arrow's tensor
    conversion: the bytes of numpy's assignment of each column into float32 rows, several
    record batches included; with nulls they come chunk by chunk, the same way."""
    feather = pytest.importorskip("pyarrow.feather")
    from floxels_ext.lidar.io import read_points
    from floxels_ext.lidar.io._arrow import xyz_rows

    g = np.random.default_rng(7)
    n = 50
    scale = 1e3 if dtype == np.float16 else 3e4  # (float16 tops out at 65504)
    vals = (g.normal(0, scale, (n, 3)) if np.issubdtype(dtype, np.floating) else g.integers(0, 200, (n, 3)))
    vals = vals.astype(dtype)
    for name, nulls in (("plain", False), ("nulls", True)):
        cols = {c: pa.array(vals[:, k], mask=(np.arange(n) == 9) if nulls and c == "y" else None)
                for k, c in enumerate("xyz")}
        path = tmp_path / f"{name}.feather"
        feather.write_feather(pa.table({**cols, "intensity": np.arange(n, dtype=np.uint8)}), str(path),
                              chunksize=16, compression="uncompressed")
        table = feather.read_table(str(path))
        assert (xyz_rows(table) is None) == nulls
        ref = np.empty((n, 3), np.float32)
        for k, c in enumerate("xyz"):
            ref[:, k] = table.column(c).to_numpy(zero_copy_only=False)
        got = read_points(path).points
        assert got.dtype == np.float32 and got.flags.writeable and got.tobytes() == ref.tobytes()


def test_feather_rows_of_mixed_types_come_chunk_by_chunk():
    from floxels_ext.lidar.io._arrow import xyz_rows

    t = pa.table({"x": np.zeros(3, np.float16), "y": np.zeros(3, np.float32), "z": np.zeros(3, np.float32)})
    assert xyz_rows(t) is None


def test_feather_rows_of_mixed_types_round_once(tmp_path):
    """x int64 beside float32 y, z: each value cast once to float32, as numpy's assignment does.
    (Arrow's tensor of mixed columns is float64: 2^60 + 2^36 + 1 through float64 lands on a
    float32 tie and rounds to even, one float32 step away.)"""
    from pyarrow import feather

    from floxels_ext.lidar.io import read_points

    x = np.array([2 ** 60 + 2 ** 36 + 1, 5, -7], np.int64)
    y, z = np.array([1.5, 2.5, 3.5], np.float32), np.array([0.25, 1.0, -2.0], np.float32)
    path = tmp_path / "315966265659927216.feather"
    feather.write_feather(pa.table({"x": x, "y": y, "z": z}), str(path), compression="uncompressed")
    ref = np.empty((3, 3), np.float32)
    ref[:, 0], ref[:, 1], ref[:, 2] = x, y, z
    assert read_points(path).points.tobytes() == ref.tobytes()
