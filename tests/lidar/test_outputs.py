"""The .npz writer of floxels run: the directly written zip equals np.savez's content."""

import zipfile

import numpy as np
import pytest

from floxels_ext.lidar.io.outputs import write_output


def test_direct_npz_reads_back_like_np_savez(tmp_path):
    g = np.random.default_rng(0)
    arrays = dict(flow=g.random((5000, 3), dtype=np.float32), mask=g.random(5000) < 0.4, pose=np.eye(4),
                  text=np.str_("h\u00e9llo" * 50), n=np.int32(5), empty=np.zeros((0, 3), np.float32),
                  fortran=np.asfortranarray(g.random((5, 4))), strided=g.random((10, 6))[:, ::2],
                  stamp=np.int64(2**40), flag=np.bool_(True))
    path = write_output(tmp_path / "a.npz", **arrays)
    assert not list(tmp_path.glob(".*.tmp"))
    with zipfile.ZipFile(path) as z:
        assert z.testzip() is None  # CRCs and headers valid
        assert sorted(z.namelist()) == sorted(k + ".npy" for k in arrays)
    np.savez(tmp_path / "ref.npz", **arrays)
    with np.load(path) as got, np.load(tmp_path / "ref.npz") as ref:
        for k in arrays:
            assert got[k].dtype == ref[k].dtype and got[k].shape == ref[k].shape, k
            np.testing.assert_array_equal(got[k], ref[k])


def test_object_arrays_fall_back_to_np_savez(tmp_path):
    path = write_output(tmp_path / "b.npz", obj=np.array([{"a": 1}], dtype=object), x=np.arange(3))
    with np.load(path, allow_pickle=True) as z:
        assert z["obj"][0] == {"a": 1}
        np.testing.assert_array_equal(z["x"], np.arange(3))
    path = write_output(tmp_path / "c.npz", compress=True, x=np.arange(3))
    with zipfile.ZipFile(path) as z:
        assert z.getinfo("x.npy").compress_type == zipfile.ZIP_DEFLATED


def test_old_outputs_module_path_still_reads_with_a_warning():
    # the README documented floxels_ext.lidar.outputs before the package split (issue 32)
    import importlib
    import sys

    from floxels_ext.lidar.io import outputs as new

    sys.modules.pop("floxels_ext.lidar.outputs", None)
    with pytest.warns(DeprecationWarning, match="lidar.io.outputs"):
        old = importlib.import_module("floxels_ext.lidar.outputs")
    assert old.read_flow_output is new.read_flow_output
