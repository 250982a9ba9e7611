"""tests/shared_data.py: ../shared's tests skip without it, fail without it in CI."""

import pytest

from shared_data import SHARED, shared_path


def test_missing_shared_file_skips_or_fails(monkeypatch):
    monkeypatch.delenv("FLOXELS_REQUIRE_SHARED", raising=False)
    with pytest.raises(pytest.skip.Exception, match="absent"):
        shared_path("no-such-file.npz")
    monkeypatch.setenv("FLOXELS_REQUIRE_SHARED", "1")
    with pytest.raises(pytest.fail.Exception, match="FLOXELS_REQUIRE_SHARED=1 requires it"):
        shared_path("no-such-file.npz")
    monkeypatch.setenv("FLOXELS_AV2_PAIR", "/no/such/file.npz")
    with pytest.raises(pytest.fail.Exception, match="FLOXELS_AV2_PAIR=/no/such/file.npz"):
        shared_path("no-such-file.npz", env="FLOXELS_AV2_PAIR")


def test_shared_is_beside_the_checkout():
    from pathlib import Path

    assert SHARED == Path(__file__).resolve().parents[2] / "shared"
