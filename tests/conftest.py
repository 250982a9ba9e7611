import pytest
import torch

import floxels_ext  # noqa: F401  (loads the ops)

CUDA = torch.cuda.is_available() and floxels_ext.ops.has_cuda_kernels()


def pytest_collection_modifyitems(config, items):
    skip = pytest.mark.skip(reason="needs a CUDA device and a CUDA build of floxels_ext")
    for item in items:
        if "cuda" in item.keywords and not CUDA:
            item.add_marker(skip)
