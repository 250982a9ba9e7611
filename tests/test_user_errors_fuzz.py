"""Property-style fuzzing (plain random generation, fixed seeds) of the two user entry points
``estimate_flow`` and ``floxels_ext.lidar.io.read_points``: random bad inputs give a clear
exception of the documented kinds, or a finite, documented result; never another exception
or a crash."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from floxels_ext import FloxelsConfig, estimate_flow
from floxels_ext.lidar.io import LidarFormatError, MissingDependencyError, read_points

CFG = FloxelsConfig(max_iters=3, patience=3)
MESSAGES: list = []
CLEAR = (ValueError, TypeError, IndexError)  # LidarFormatError, GridTooLargeError are ValueErrors


def _random_scan(rng):
    """A (mostly) bad scan of some kind, and whether estimate_flow may accept it."""
    bad = ["empty", "one", "nan_rows", "all_nan", "inf", "huge", "far", "int", "bool", "complex", "shape2", "shape4",
           "flat", "3d", "list", "none", "str", "tensor", "half", "transposed"]
    # mostly valid scans, so that whole windows are often accepted and run
    kind = "ok" if rng.random() < 0.75 else rng.choice(["ok64"] + bad)
    n = int(rng.choice([1, 5, 40]))
    p = rng.uniform(-5, 5, (n, 3)).astype(np.float32)
    if kind == "ok":
        return p
    if kind == "ok64":
        return p.astype(np.float64)
    if kind == "empty":
        return np.zeros((0, 3), np.float32)
    if kind == "one":
        return p[:1]
    if kind == "nan_rows":
        p[rng.random(n) < 0.3] = np.nan
        return p
    if kind == "all_nan":
        return np.full((n, 3), np.nan, np.float32)
    if kind == "inf":
        p[0, int(rng.integers(3))] = rng.choice([np.inf, -np.inf])
        return p
    if kind == "huge":
        return p * 1e30
    if kind == "far":  # absurd extent: the distance transform would not fit
        p[0] = 1e6
        return p
    if kind == "int":
        return p.astype(np.int32)
    if kind == "bool":
        return p > 0
    if kind == "complex":
        return p.astype(np.complex64)
    if kind == "shape2":
        return p[:, :2]
    if kind == "shape4":
        return np.c_[p, p[:, :1]]
    if kind == "flat":
        return p.ravel()
    if kind == "3d":
        return p[None]
    if kind == "list":
        return p.tolist()
    if kind == "none":
        return None
    if kind == "str":
        return "scan.bin"
    if kind == "tensor":
        return torch.from_numpy(p)
    if kind == "half":
        return torch.from_numpy(p).half()
    return p.T.copy()  # transposed


def test_fuzz_estimate_flow():
    rng = np.random.default_rng(1234)
    outcomes = {"ok": 0, "error": 0}
    for _ in range(150):
        k = int(rng.choice([0, 1, 2, 3, 3, 3, 5, 5, 14]))
        scans = [_random_scan(rng) for _ in range(k)]
        target = rng.choice([None, None, 0, -1, k, -k - 1, 1.5, "x"])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                flow = estimate_flow(scans, target, CFG, device="cpu")
            except CLEAR as e:
                assert str(e), "an error must say what is wrong"
                MESSAGES.append(f"{type(e).__name__}: {e}")
                outcomes["error"] += 1
                continue
        # accepted: one finite flow row per finite input row, NaN for the others
        t = len(scans) // 2 if target is None else int(target)
        src = scans[t]
        src_np = src.float().numpy() if isinstance(src, torch.Tensor) else np.asarray(src, np.float64)
        out = flow.float().numpy() if isinstance(flow, torch.Tensor) else flow
        assert out.shape == src_np.shape
        finite = np.isfinite(src_np).all(1)
        assert np.isfinite(out[finite]).all() and np.isnan(out[~finite]).all()
        outcomes["ok"] += 1
    assert outcomes["ok"] >= 10 and outcomes["error"] >= 40, outcomes


def _valid_file_bytes(suffix: str, rng) -> bytes:
    pts = rng.uniform(-20, 20, (30, 3)).astype(np.float32)
    if suffix == ".bin":
        return np.c_[pts, np.zeros(30, np.float32)].astype(np.float32).tobytes()
    if suffix == ".pcd":
        head = ("# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 30\n"
                "HEIGHT 1\nPOINTS 30\nDATA binary\n")
        return head.encode() + pts.tobytes()
    if suffix == ".ply":
        head = "ply\nformat binary_little_endian 1.0\nelement vertex 30\nproperty float x\nproperty float y\n" \
               "property float z\nend_header\n"
        return head.encode() + pts.tobytes()
    import io

    buf = io.BytesIO()
    if suffix == ".npy":
        np.save(buf, pts)
    else:
        np.savez(buf, points=pts)
    return buf.getvalue()


@pytest.mark.parametrize("suffix", [".bin", ".npy", ".npz", ".pcd", ".ply", ".feather"])
def test_fuzz_read_points(tmp_path, suffix):
    rng = np.random.default_rng([ord(c) for c in suffix])
    good = _valid_file_bytes(suffix, rng) if suffix != ".feather" else b"ARROW1\0\0" + rng.bytes(200)
    for k in range(60):
        kind = k % 6
        if kind == 0:
            data = b""
        elif kind == 1:
            data = rng.bytes(int(rng.integers(1, 4000)))
        elif kind == 2:  # truncated
            data = good[:int(rng.integers(1, len(good)))]
        elif kind == 3:  # bytes flipped
            b = bytearray(good)
            for i in rng.integers(0, len(b), int(rng.integers(1, 20))):
                b[i] = int(rng.integers(256))
            data = bytes(b)
        elif kind == 4:  # header garbage + good tail
            data = rng.bytes(int(rng.integers(1, 64))) + good
        else:
            data = good
        path = tmp_path / f"f{k}{suffix}"
        path.write_bytes(data)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                scan = read_points(path, bin_columns=int(rng.choice([3, 4, 5])) if suffix == ".bin" and k % 7 == 0
                                   else None)
            except (LidarFormatError, MissingDependencyError) as e:
                assert str(path) in str(e) or isinstance(e, MissingDependencyError), e
                continue
            except ValueError as e:  # bad bin_columns argument
                assert "bin_columns" in str(e)
                continue
        assert scan.points.dtype == np.float32 and scan.points.ndim == 2 and scan.points.shape[1] == 3
        assert len(scan) >= 1
