"""Lidar frame readers on tiny files written here: every format and variant, corrupt input."""

import struct

import numpy as np
import pytest

from floxels_ext.lidar.io import LidarFormatError, MissingDependencyError, read_points
from floxels_ext.lidar.io.readers import lzf_decompress, natural_key
from floxels_ext.lidar.io.writers import write_ply


def _pts(n=7, seed=0):
    return np.random.default_rng(seed).normal(scale=10, size=(n, 3)).astype(np.float32)


# ----------------------------------------------------------------------------- .bin
def test_bin_kitti_and_nuscenes(tmp_path):
    p = _pts(7)
    kitti = np.c_[p, np.linspace(0, 1, 7)].astype(np.float32)
    kitti.tofile(tmp_path / "k.bin")
    s = read_points(tmp_path / "k.bin")
    np.testing.assert_array_equal(s.points, p)
    np.testing.assert_array_equal(s.fields["intensity"], kitti[:, 3])
    nus = np.c_[p, np.linspace(0, 1, 7), np.arange(7) % 32].astype(np.float32)
    nus.tofile(tmp_path / "n.bin")
    s = read_points(tmp_path / "n.bin")
    np.testing.assert_array_equal(s.points, p)
    np.testing.assert_array_equal(s.fields["ring"], np.arange(7) % 32)


def test_bin_ambiguous_size_and_override(tmp_path):
    p = _pts(20, 1)  # 20 rows x 4 = 80 floats: fits 4 and 5 columns (16 rows)
    a4 = np.c_[p, np.full(20, 0.5)].astype(np.float32)
    a4.tofile(tmp_path / "a.bin")
    np.testing.assert_array_equal(read_points(tmp_path / "a.bin").points, p)
    p5 = _pts(16, 2)
    a5 = np.c_[p5, np.full(16, 0.25), np.arange(16)].astype(np.float32)
    a5.tofile(tmp_path / "b.bin")
    np.testing.assert_array_equal(read_points(tmp_path / "b.bin").points, p5)
    # explicit override wins
    assert read_points(tmp_path / "b.bin", bin_columns=4).points.shape == (20, 3)


def test_bin_errors(tmp_path):
    (tmp_path / "t.bin").write_bytes(b"\0" * 28)  # 7 floats: neither 4 nor 5 columns
    with pytest.raises(LidarFormatError, match=r"t\.bin.*truncated"):
        read_points(tmp_path / "t.bin")
    (tmp_path / "e.bin").write_bytes(b"")
    with pytest.raises(LidarFormatError, match=r"e\.bin.*no points"):
        read_points(tmp_path / "e.bin")


def test_truncated_kitti_bin_read_as_5_columns_says_truncated(tmp_path):
    # a 4-column file cut at a size 20 divides (not 16 or 12) read as 5 columns; the hint was
    # "pass --bin-columns 3 if the rows are x y z only", a count its size does not allow
    rng = np.random.default_rng(0)
    az = np.sort(rng.uniform(-np.pi, np.pi, 1000))
    r = rng.uniform(5, 40, 1000)
    a = np.c_[r * np.cos(az), r * np.sin(az), rng.uniform(-2, 1, 1000), rng.uniform(0, 1, 1000)].astype(np.float32)
    (tmp_path / "000003.bin").write_bytes(a.tobytes()[:15980])
    with pytest.raises(LidarFormatError, match=r"000003\.bin.*4th column is negative.*15980 bytes.*truncated") as e:
        read_points(tmp_path / "000003.bin")
    assert "--bin-columns 3" not in str(e.value)


def test_bin_that_shrinks_while_read_names_the_file(tmp_path, monkeypatch):
    """The size is listed before the read (it picks the column count); a file cut shorter in
    between (a copy still being written, a sync) is an error naming it, not a frame of
    uninitialised rows."""
    import floxels_ext.lidar.io.readers as readers

    path = tmp_path / "000001.bin"
    np.c_[_pts(8), np.zeros(8, np.float32)].astype(np.float32).tofile(path)
    real = readers.os.path.getsize
    monkeypatch.setattr(readers.os.path, "getsize", lambda p: real(p) + 16 * 8 if str(p) == str(path) else real(p))
    with pytest.raises(LidarFormatError, match=r"000001\.bin.*shrank"):
        read_points(path)


def test_nan_rows_are_kept_in_order(tmp_path):
    p = _pts(8)
    p[3] = np.nan
    p[5, 1] = np.inf
    np.c_[p, np.zeros(8)].astype(np.float32).tofile(tmp_path / "x.bin")
    s = read_points(tmp_path / "x.bin")
    assert len(s) == 8
    np.testing.assert_array_equal(s.valid, [1, 1, 1, 0, 1, 0, 1, 1])


# ----------------------------------------------------------------------------- .npy / .npz
def test_npy_plain_and_structured(tmp_path):
    p = _pts()
    np.save(tmp_path / "a.npy", np.c_[p, np.ones(7)].astype(np.float64))
    s = read_points(tmp_path / "a.npy")
    assert s.points.dtype == np.float32 and s.points.shape == (7, 3)
    np.testing.assert_allclose(s.points, p)
    rec = np.zeros(7, dtype=[("intensity", "u1"), ("z", "f8"), ("x", "f4"), ("y", "f4")])
    rec["x"], rec["y"], rec["z"] = p[:, 0], p[:, 1], p[:, 2]
    np.save(tmp_path / "r.npy", rec)
    s = read_points(tmp_path / "r.npy")
    np.testing.assert_allclose(s.points, p)
    assert "intensity" in s.fields
    np.save(tmp_path / "bad.npy", np.zeros((5, 2)))
    with pytest.raises(LidarFormatError, match=r"bad\.npy.*\(N, >=3\)"):
        read_points(tmp_path / "bad.npy")


def test_npz_keys_and_pose(tmp_path):
    p = _pts()
    np.savez(tmp_path / "a.npz", points=p, pose=np.eye(4), intensity=np.ones(7))
    s = read_points(tmp_path / "a.npz")
    np.testing.assert_array_equal(s.points, p)
    np.testing.assert_array_equal(s.pose, np.eye(4))
    np.savez(tmp_path / "b.npz", meta=np.zeros(3), cloud=p)  # no 'points': first (N, >=3) array
    np.testing.assert_array_equal(read_points(tmp_path / "b.npz").points, p)
    np.savez(tmp_path / "c.npz", meta=np.zeros(3))
    with pytest.raises(LidarFormatError, match=r"c\.npz.*no 'points'"):
        read_points(tmp_path / "c.npz")
    np.savez(tmp_path / "d.npz", points=p, pose=np.eye(3))
    with pytest.raises(LidarFormatError, match=r"d\.npz.*pose"):
        read_points(tmp_path / "d.npz")
    np.savez(tmp_path / "e.npz", points=np.zeros((0, 3)))
    with pytest.raises(LidarFormatError, match=r"e\.npz.*no points"):
        read_points(tmp_path / "e.npz")


# ----------------------------------------------------------------------------- .pcd
def _pcd_header(fields, sizes, types, counts, n, data):
    return (f"# .PCD v0.7\nVERSION 0.7\nFIELDS {' '.join(fields)}\nSIZE {' '.join(map(str, sizes))}\n"
            f"TYPE {' '.join(types)}\nCOUNT {' '.join(map(str, counts))}\nWIDTH {n}\nHEIGHT 1\n"
            f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {data}\n").encode()


def _lzf_literals(data: bytes) -> bytes:
    """Valid LZF made only of literal runs (what a trivial compressor may emit)."""
    out = bytearray()
    for i in range(0, len(data), 32):
        chunk = data[i:i + 32]
        out.append(len(chunk) - 1)
        out += chunk
    return bytes(out)


def test_pcd_ascii_binary_compressed(tmp_path):
    p = _pts(6).astype(np.float64)
    inten = np.arange(6, dtype=np.uint16)
    # fields in an unusual order and types: intensity (u2), z (f8), x (f4), y (f4), a 2-count field
    dt = np.dtype([("intensity", "<u2"), ("z", "<f8"), ("x", "<f4"), ("y", "<f4"), ("n", "<f4", (2,))])
    rec = np.zeros(6, dt)
    rec["intensity"], rec["z"], rec["x"], rec["y"] = inten, p[:, 2], p[:, 0], p[:, 1]
    hdr = lambda mode: _pcd_header(["intensity", "z", "x", "y", "n"], [2, 8, 4, 4, 4], ["U", "F", "F", "F", "F"],
                                   [1, 1, 1, 1, 2], 6, mode)
    (tmp_path / "b.pcd").write_bytes(hdr("binary") + rec.tobytes())
    lines = "\n".join(f"{r['intensity']} {r['z'].item()!r} {r['x'].item()!r} {r['y'].item()!r} 0 0" for r in rec)
    (tmp_path / "a.pcd").write_bytes(hdr("ascii") + lines.encode() + b"\n")
    colmajor = b"".join(np.ascontiguousarray(rec[n]).tobytes() for n in dt.names)
    comp = _lzf_literals(colmajor)
    (tmp_path / "c.pcd").write_bytes(hdr("binary_compressed") + struct.pack("<II", len(comp), len(colmajor)) + comp)
    for name in ("a.pcd", "b.pcd", "c.pcd"):
        s = read_points(tmp_path / name)
        np.testing.assert_allclose(s.points, p.astype(np.float32), err_msg=name)
        np.testing.assert_array_equal(s.fields["intensity"], inten)
    # truncated binary data, missing fields, bad compressed data
    (tmp_path / "t.pcd").write_bytes(hdr("binary") + rec.tobytes()[:-5])
    with pytest.raises(LidarFormatError, match=r"t\.pcd.*truncated"):
        read_points(tmp_path / "t.pcd")
    (tmp_path / "m.pcd").write_bytes(_pcd_header(["x", "y"], [4, 4], ["F", "F"], [1, 1], 1, "ascii") + b"1 2\n")
    with pytest.raises(LidarFormatError, match=r"m\.pcd.*'z'"):
        read_points(tmp_path / "m.pcd")
    (tmp_path / "z.pcd").write_bytes(hdr("binary_compressed") + struct.pack("<II", 4, len(colmajor)) + b"\x1f\0\0\0")
    with pytest.raises(LidarFormatError, match=r"z\.pcd.*corrupt"):
        read_points(tmp_path / "z.pcd")
    (tmp_path / "h.pcd").write_bytes(b"VERSION 0.7\nFIELDS x y z\n")
    with pytest.raises(LidarFormatError, match=r"h\.pcd.*DATA"):
        read_points(tmp_path / "h.pcd")


def test_lzf_back_references():
    # 'abc' literal, then a back-reference of length 9 at distance 3 (overlapping copy)
    data = bytes([2]) + b"abc" + bytes([(7 << 5) | 0, 0, 2])  # len = 7 + 0 + 2 = 9, offset 2 + 1 = 3
    assert lzf_decompress(data, 12) == b"abc" * 4
    with pytest.raises(ValueError):
        lzf_decompress(bytes([0x20, 0x05]), 3)  # reference before the start


# ----------------------------------------------------------------------------- .ply
def test_ply_variants(tmp_path):
    p = _pts(5)
    write_ply(tmp_path / "b.ply", p, intensity=np.arange(5, dtype=np.uint8))
    write_ply(tmp_path / "a.ply", p, ascii=True, intensity=np.arange(5, dtype=np.uint8))
    for name in ("a.ply", "b.ply"):
        s = read_points(tmp_path / name)
        np.testing.assert_allclose(s.points, p)
        np.testing.assert_array_equal(s.fields["intensity"], np.arange(5))
    # big endian, double coordinates in a different order, a 'face' element BEFORE the vertices
    dt = np.dtype([("z", ">f8"), ("x", ">f8"), ("y", ">f8")])
    rec = np.zeros(5, dt)
    rec["x"], rec["y"], rec["z"] = p[:, 0], p[:, 1], p[:, 2]
    faces = b"".join(struct.pack(">B3i", 3, 0, 1, 2) for _ in range(2))
    hdr = (b"ply\nformat binary_big_endian 1.0\ncomment x\nelement face 2\nproperty list uchar int vertex_indices\n"
           b"element vertex 5\nproperty double z\nproperty double x\nproperty double y\nend_header\n")
    (tmp_path / "be.ply").write_bytes(hdr + faces + rec.tobytes())
    np.testing.assert_allclose(read_points(tmp_path / "be.ply").points, p)
    # ascii with an element before the vertices
    hdr = (b"ply\nformat ascii 1.0\nelement camera 1\nproperty float k\nelement vertex 2\nproperty float x\n"
           b"property float y\nproperty float z\nend_header\n")
    (tmp_path / "c.ply").write_bytes(hdr + b"7\n1 2 3\n4 5 6\n")
    np.testing.assert_allclose(read_points(tmp_path / "c.ply").points, [[1, 2, 3], [4, 5, 6]])
    # truncated binary, no vertex element, not a ply
    (tmp_path / "t.ply").write_bytes((tmp_path / "b.ply").read_bytes()[:-3])
    with pytest.raises(LidarFormatError, match=r"t\.ply.*truncated"):
        read_points(tmp_path / "t.ply")
    (tmp_path / "n.ply").write_bytes(b"ply\nformat ascii 1.0\nelement face 0\nend_header\n")
    with pytest.raises(LidarFormatError, match=r"n\.ply.*vertex"):
        read_points(tmp_path / "n.ply")
    (tmp_path / "g.ply").write_bytes(b"garbage")
    with pytest.raises(LidarFormatError, match=r"g\.ply"):
        read_points(tmp_path / "g.ply")


# ----------------------------------------------------------------------------- .feather
def test_feather_av2(tmp_path):
    pa = pytest.importorskip("pyarrow")
    feather = pytest.importorskip("pyarrow.feather")
    p = _pts(9)
    t = pa.table({"x": p[:, 0].astype(np.float16).astype(np.float32), "y": p[:, 1], "z": p[:, 2],
                  "intensity": np.arange(9, dtype=np.uint8), "laser_number": np.arange(9, dtype=np.uint8)})
    path = tmp_path / "315966265659927216.feather"
    feather.write_feather(t, str(path))
    s = read_points(path)
    assert s.timestamp_ns == 315966265659927216 and len(s) == 9
    np.testing.assert_allclose(s.points[:, 1:], p[:, 1:])
    assert set(s.fields) == {"intensity", "laser_number"}
    feather.write_feather(pa.table({"a": [1.0]}), str(tmp_path / "bad.feather"))
    with pytest.raises(LidarFormatError, match=r"bad\.feather.*'x'"):
        read_points(tmp_path / "bad.feather")
    (tmp_path / "c.feather").write_bytes(b"ARROW1 but not really")
    with pytest.raises(LidarFormatError, match=r"c\.feather"):
        read_points(tmp_path / "c.feather")
    feather.write_feather(pa.table({"x": ["a"], "y": [1.0], "z": [2.0]}), str(tmp_path / "s.feather"))
    with pytest.raises(LidarFormatError, match=r"s\.feather: column 'x' holds string"):
        read_points(tmp_path / "s.feather")


def test_feather_column_types_read_exactly(tmp_path):
    """AV2's float16 columns (exact in float32), float64 (rounded once) and integers, as before."""
    pa = pytest.importorskip("pyarrow")
    feather = pytest.importorskip("pyarrow.feather")
    g = np.random.default_rng(3)
    x16 = g.normal(0, 30, 50).astype(np.float16)
    y64 = g.normal(0, 30, 50)
    z64 = np.concatenate([[np.nan], g.normal(0, 2, 49)])
    ints = np.arange(50, dtype=np.int32) - 7
    feather.write_feather(pa.table({"x": x16, "y": y64, "z": z64}), str(tmp_path / "a.feather"))
    s = read_points(tmp_path / "a.feather")
    assert s.points.dtype == np.float32
    np.testing.assert_array_equal(s.points, np.c_[x16.astype(np.float64), y64, z64].astype(np.float32))
    feather.write_feather(pa.table({"x": ints, "y": ints, "z": ints}), str(tmp_path / "i.feather"))
    np.testing.assert_array_equal(read_points(tmp_path / "i.feather").points, np.c_[ints, ints, ints])


def test_feather_chunks_read_as_the_whole_columns(tmp_path):
    """Files of several record batches (AV2's, bench_run's: 64k rows each), nulls in some of
    them, read chunk by chunk: the same bytes as the ChunkedArray conversions of before."""
    pa = pytest.importorskip("pyarrow")
    feather = pytest.importorskip("pyarrow.feather")
    g = np.random.default_rng(5)
    n = 70
    cols = {"x": pa.array(g.normal(0, 30, n).astype(np.float16)),
            "y": pa.array(g.normal(0, 30, n)),
            "z": pa.array([None if i % 17 == 3 else int(i) - 20 for i in range(n)], pa.int32()),
            "intensity": pa.array(g.integers(0, 255, n).astype(np.uint8)),
            "offset_ns": pa.array([None if i == 40 else i * 1000 for i in range(n)], pa.int64()),
            "flag": pa.array([i % 3 == 0 for i in range(n)]),
            "tag": pa.array([f"t{i}" for i in range(n)])}
    table = pa.table(cols)
    path = tmp_path / "1.feather"
    feather.write_feather(table, str(path), chunksize=16, compression="uncompressed")
    table = feather.read_table(str(path))
    assert table.column("x").num_chunks == 5
    s = read_points(path)
    xyz = np.empty((n, 3), np.float32)
    for k, c in enumerate("xyz"):
        xyz[:, k] = table.column(c).to_numpy(zero_copy_only=False)
    assert s.points.tobytes() == xyz.tobytes() and np.isnan(s.points[3, 2])
    assert list(s.fields) == ["intensity", "offset_ns", "flag", "tag"]
    for c, v in s.fields.items():
        ref = table.column(c).to_numpy(zero_copy_only=False)
        assert v.dtype == ref.dtype and v.shape == ref.shape
        assert v.tobytes() == ref.tobytes() if ref.dtype != object else list(v) == list(ref)


def test_feather_without_pyarrow_says_how_to_install(tmp_path, monkeypatch):
    import builtins

    real = builtins.__import__

    def fake(name, *a, **k):
        if name.startswith("pyarrow"):
            raise ImportError("No module named 'pyarrow'")
        return real(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", fake)
    monkeypatch.setattr("importlib.import_module", lambda name, *a: fake(name))
    (tmp_path / "1.feather").write_bytes(b"x")
    with pytest.raises(MissingDependencyError, match=r"floxels_ext\[av2\].*pip install pyarrow"):
        read_points(tmp_path / "1.feather")


# ----------------------------------------------------------------------------- dispatch
def test_unknown_extension_and_missing_file(tmp_path):
    (tmp_path / "a.xyz").write_text("1 2 3\n")
    with pytest.raises(LidarFormatError, match=r"a\.xyz.*unknown lidar file extension"):
        read_points(tmp_path / "a.xyz")
    with pytest.raises(LidarFormatError, match=r"nope\.bin.*no such file"):
        read_points(tmp_path / "nope.bin")
    (tmp_path / "dir.bin").mkdir()
    with pytest.raises(LidarFormatError, match=r"dir\.bin.*not a regular file"):
        read_points(tmp_path / "dir.bin")
    pytest.importorskip("pyarrow")
    with pytest.raises(LidarFormatError, match=r"1\.feather.*no such file"):
        read_points(tmp_path / "1.feather")
    (tmp_path / "z.npy").write_bytes(b"\x93NUMPY garbage")
    with pytest.raises(LidarFormatError, match=r"z\.npy"):
        read_points(tmp_path / "z.npy")


def test_natural_order():
    names = ["f10.bin", "f2.bin", "f1.bin", "g.bin"]
    assert sorted(names, key=natural_key) == ["f1.bin", "f2.bin", "f10.bin", "g.bin"]
