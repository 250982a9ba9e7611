from pathlib import Path

import pytest
import torch

import floxels_ext  # noqa: F401  (loads the ops)
from shared_data import shared_path

CUDA = torch.cuda.is_available() and floxels_ext.ops.has_cuda_kernels()


def pytest_collection_modifyitems(config, items):
    skip = pytest.mark.skip(reason="needs a CUDA device and a CUDA build of floxels_ext")
    for item in items:
        if "cuda" in item.keywords and not CUDA:
            item.add_marker(skip)


@pytest.fixture(scope="session")
def av2_pair_path() -> Path:
    """The shared Argoverse 2 pair (../shared/data/av2_pair beside the checkout, or the file
    FLOXELS_AV2_PAIR names); skips without it, fails with FLOXELS_REQUIRE_SHARED=1 (CI)."""
    return shared_path("data", "av2_pair", "av2_7fab2350_pair.npz", env="FLOXELS_AV2_PAIR")
