"""The .bin reader's scan-order score (``readers._disorder``, made cheaper for issue 42/44's
engine cost; now the compiled op ``scan_disorder``) equals its numpy formula to the bit:
np.percentile's quartiles and np.median's median, so the column-count check refuses exactly
what it refused before."""

import numpy as np
import pytest

from floxels_ext.lidar.io import readers


def _disorder_reference(a: np.ndarray, rows: int) -> float:
    xyz = a[:rows, :3].astype(np.float64)
    xyz = xyz[np.isfinite(xyz).all(1)]
    if xyz.shape[0] < 16:
        return float("nan")
    q75, q25 = np.percentile(xyz, [75, 25], axis=0)
    step = np.median(np.abs(np.diff(xyz, axis=0)), axis=0)
    return float(np.median(step / np.maximum(q75 - q25, 1e-6)))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("kind", ["noise", "walk", "ties", "nonfinite", "huge"])
def test_disorder_equals_numpy_formula(kind, dtype):
    rng = np.random.default_rng(42)
    for _ in range(150):
        n, c, rows = int(rng.integers(1, 1500)), int(rng.integers(3, 9)), int(rng.integers(16, 2000))
        if kind == "noise":
            a = rng.normal(size=(n, c))
        elif kind == "walk":
            a = np.cumsum(rng.normal(size=(n, c)), 0)
        elif kind == "ties":
            a = rng.integers(-3, 3, size=(n, c))
        elif kind == "huge":  # steps beyond float32's range (computed in float64)
            a = rng.normal(size=(n, c)) * 1e37
        else:
            a = rng.normal(size=(n, c)) * 100
            a[rng.random((n, c)) < 0.05] = np.nan
            a[rng.random((n, c)) < 0.01] = np.inf
        a = a.astype(dtype)
        ref, got = _disorder_reference(a, rows), readers._disorder(a, rows)
        assert (np.isnan(ref) and np.isnan(got)) or ref == got, (n, c, rows, ref, got)


def test_disorder_of_file_rows():
    """As the reader calls it: 8192 rows of a scan-ordered x y z intensity file, read with
    each column count (strided x y z columns of the flat file), score for score."""
    rng = np.random.default_rng(3)
    t = np.linspace(0, 40 * np.pi, 30_000)
    rows = np.stack([20 * np.cos(t), 20 * np.sin(t), rng.normal(-1.7, 0.05, t.size), rng.random(t.size)], 1)
    flat = rows.astype(np.float32).reshape(-1)
    for c in range(3, 9):
        a = flat[:len(flat) // c * c].reshape(-1, c)
        ref, got = _disorder_reference(a, 8192), readers._disorder(a, 8192)
        assert ref == got, (c, ref, got)
