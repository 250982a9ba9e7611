import os
from pathlib import Path

import pytest
import torch

import floxels_ext  # noqa: F401  (loads the ops)

CUDA = torch.cuda.is_available() and floxels_ext.ops.has_cuda_kernels()


def pytest_collection_modifyitems(config, items):
    skip = pytest.mark.skip(reason="needs a CUDA device and a CUDA build of floxels_ext")
    for item in items:
        if "cuda" in item.keywords and not CUDA:
            item.add_marker(skip)


@pytest.fixture(scope="session")
def av2_pair_path() -> Path:
    """The shared Argoverse 2 pair (shared/data/av2_pair, FLOXELS_AV2_PAIR); skips without it."""
    here = Path(__file__).resolve().parents[1]
    for p in (os.environ.get("FLOXELS_AV2_PAIR"), here / "shared/data/av2_pair/av2_7fab2350_pair.npz",
              here.parent / "shared/data/av2_pair/av2_7fab2350_pair.npz",
              "/work/shared/data/av2_pair/av2_7fab2350_pair.npz"):
        if p and Path(p).is_file():
            return Path(p)
    pytest.skip("the shared Argoverse 2 pair (shared/data/av2_pair) is not available")
