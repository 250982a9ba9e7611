"""Where the tests find ``../shared`` (the paper's text, the real KITTI sweeps and the Argoverse 2
pair): beside the checkout, as on the development machines and in CI. Without it those tests
skip, unless ``FLOXELS_REQUIRE_SHARED=1`` (``.ci/run`` sets it: CI has ``../shared``), where a
missing file fails them instead, so that they cannot skip unnoticed where they must run."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

SHARED = Path(__file__).resolve().parents[2] / "shared"


def shared_path(*parts: str, env: str | None = None) -> Path:
    """``../shared/<parts>`` (or the file the environment variable ``env`` names, if set);
    skips the test when it is absent (fails with ``FLOXELS_REQUIRE_SHARED=1``)."""
    given = os.environ.get(env) if env else None
    path = Path(given) if given else SHARED.joinpath(*parts)
    if not path.exists():
        where = f"{env}={given}" if given else f"../shared/{'/'.join(parts)} beside the checkout"
        if os.environ.get("FLOXELS_REQUIRE_SHARED") == "1":
            pytest.fail(f"{path} is missing ({where}); FLOXELS_REQUIRE_SHARED=1 requires it")
        pytest.skip(f"{path} is absent ({where})")
    return path
