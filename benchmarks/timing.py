"""What every timing benchmark needs around a timed region."""

from __future__ import annotations

import torch


def sync_device(dev: torch.device | str) -> None:
    """Wait for the device's queued work (CUDA kernels run asynchronously); a no-op on the CPU."""
    dev = torch.device(dev)
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)
