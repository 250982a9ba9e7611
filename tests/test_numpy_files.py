"""``floxels_ext.numpy_files``: every .npy/.npz read of the package behind one lock (numpy's
header parse with ``ast`` is not safe from several threads on CPython 3.11, gh-106905)."""

import threading

import numpy as np
import pytest

from floxels_ext.numpy_files import load_npy, open_npz


def test_reads_from_many_threads_return_the_arrays(tmp_path):
    arrays = {f"a{i}": np.arange(i * 10, dtype=np.float32).reshape(-1, 2) for i in range(1, 6)}
    np.savez_compressed(tmp_path / "f.npz", **arrays)
    np.save(tmp_path / "g.npy", np.eye(4))
    bad = []

    def work():
        for _ in range(40):
            with open_npz(tmp_path / "f.npz") as z:
                got = {k: z[k] for k in z.files}
            if set(got) != set(arrays) or any(not np.array_equal(got[k], v) for k, v in arrays.items()):
                bad.append("npz")
            if not np.array_equal(load_npy(tmp_path / "g.npy"), np.eye(4)):
                bad.append("npy")

    threads = [threading.Thread(target=work) for _ in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not bad


def test_a_failed_read_releases_the_lock(tmp_path):
    (tmp_path / "broken.npz").write_bytes(b"not a zip")
    with pytest.raises(Exception):
        with open_npz(tmp_path / "broken.npz") as z:
            z.files
    with pytest.raises(Exception):
        load_npy(tmp_path / "broken.npz")
    np.save(tmp_path / "ok.npy", np.arange(3))
    assert load_npy(tmp_path / "ok.npy").tolist() == [0, 1, 2]  # (a held lock would hang here)


@pytest.mark.parametrize("content, says", [(b"", "empty file"), (b"garbage\n", "not a .npy file"),
                                           (b"<html>404</html>", "not a .npy file")])
def test_a_file_that_is_no_npy_says_so_not_pickled_data(tmp_path, content, says):
    # np.load took such files for pickles ("load it unsafely using allow_pickle=") or raised EOFError
    (tmp_path / "x.npy").write_bytes(content)
    with pytest.raises(ValueError, match=says) as e:
        load_npy(tmp_path / "x.npy")
    assert "pickle" not in str(e.value)
    (tmp_path / "x.npz").write_bytes(content)
    with pytest.raises(ValueError, match=says.replace("npy", "npz")):
        with open_npz(tmp_path / "x.npz"):
            pass


def test_npy_and_npz_swapped_are_named(tmp_path):
    np.save(tmp_path / "a.npy", np.eye(3))
    np.savez(tmp_path / "b.npz", a=np.eye(3))
    (tmp_path / "a.npz").write_bytes((tmp_path / "a.npy").read_bytes())
    (tmp_path / "b.npy").write_bytes((tmp_path / "b.npz").read_bytes())
    with pytest.raises(ValueError, match="a .npy array, not a .npz archive"):
        with open_npz(tmp_path / "a.npz"):
            pass
    with pytest.raises(ValueError, match="a .npz .zip. archive, not a .npy array"):
        load_npy(tmp_path / "b.npy")
