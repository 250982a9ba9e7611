"""Loads the compiled op library once; every ops module goes through ``ops_ns``."""

from __future__ import annotations

import torch  # noqa: F401  (torch must be imported before _C: _C links libtorch)

try:
    from floxels_ext import _C  # noqa: F401  (registers torch.ops.floxels.* on import)
except ImportError as exc:  # pragma: no cover - only hit on broken installs
    raise ImportError(
        "floxels_ext: the compiled extension floxels_ext._C could not be loaded "
        f"({exc}). Build it against the installed torch with "
        "`pip install --no-build-isolation .` (see README)."
    ) from exc

ops_ns = torch.ops.floxels


def has_cuda_kernels() -> bool:
    """True when this build contains the CUDA implementations."""
    return torch._C._dispatch_has_kernel_for_dispatch_key("floxels::edt", "CUDA")
