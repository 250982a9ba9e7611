"""Small host-made constants on a device without blocking the host.

``torch.tensor(values, device="cuda")`` copies from pageable memory and synchronises the
current stream; a pageable ``non_blocking`` copy may too (the driver stages pageable memory
and can wait for the stream). On a stream that queues behind the optimiser (a pipelined
batch's preparation) either made the host wait for the device's earlier work. A page-locked
source makes the copy truly asynchronous; PyTorch's caching host allocator keeps that memory
until the copy has run and reuses it after.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

__all__ = ["device_values"]


def device_values(values: Sequence, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """``torch.tensor(values, dtype=dtype)`` on ``device``; on CUDA copied from page-locked
    memory, queued on the current stream (the host waits for nothing)."""
    device = torch.device(device)
    if device.type != "cuda":
        return torch.tensor(values, dtype=dtype, device=device)
    return torch.tensor(values, dtype=dtype, pin_memory=True).to(device, non_blocking=True)
