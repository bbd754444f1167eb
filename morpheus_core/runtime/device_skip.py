"""Skipping an optimiser step on a flag that stays on the device.

A guard that asks the host "were these gradients finite?" stalls the CPU until the GPU has caught
up, every step. Fused optimisers (``torch.optim.Adam(fused=True)``) read a ``found_inf`` tensor
instead and leave parameters, moments and the step count untouched where it is set, the same
mechanism ``torch.amp.GradScaler`` uses; so the decision never leaves the device.
"""

from __future__ import annotations

import torch
from torch import Tensor


def nonfinite(grads: list[Tensor], device: torch.device, inv_scale: Tensor | None = None) -> Tensor:
    """Whether any of ``grads`` holds NaN/Inf (a bool on ``device``); multiplies them by ``inv_scale``
    when given (the loss scale's inverse), in the same pass."""
    found = torch.zeros((), dtype=torch.float32, device=device)
    inv = inv_scale if inv_scale is not None else torch.ones((), dtype=torch.float32, device=device)
    by_dtype: dict[torch.dtype, list[Tensor]] = {}
    for g in grads:
        by_dtype.setdefault(g.dtype, []).append(g)
    for group in by_dtype.values():
        torch._amp_foreach_non_finite_check_and_unscale_(group, found, inv)
    return found > 0


def skips_on_device(opt: torch.optim.Optimizer) -> bool:
    """Whether ``opt`` can skip a step on a device flag (fused optimisers read ``found_inf``)."""
    return bool(opt.defaults.get("fused")) and bool(getattr(opt, "_step_supports_amp_scaling", False))


def step_or_skip(opt: torch.optim.Optimizer, bad: Tensor) -> None:
    """``opt.step()`` unless ``bad`` (a bool on the device): without a host sync for fused
    optimisers; others ask the host."""
    if skips_on_device(opt):
        opt.found_inf = bad.float()  # type: ignore[attr-defined]
        try:
            opt.step()
        finally:
            del opt.found_inf  # type: ignore[attr-defined]
    elif not bool(bad):
        opt.step()
