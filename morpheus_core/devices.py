"""Which torch device a configuration's device name means, whether its kernels are compiled, and
how host-drawn random values reach it without stalling the host."""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

# ``torch.compile`` of hot pure-tensor kernels (the hash-grid encode): on CUDA only — it fuses the
# gather/weight arithmetic into a few Triton kernels (DESIGN.md §7: 14 → 2 ms per 2^18 points) —
# while CPU keeps the eager code (inductor's CPU path needs a compiler and pays minutes of
# compilation for little gain). ``MORPHEUS_COMPILE=0`` turns it off (debugging, benchmarks' "before").
_compiled: dict[Callable[..., Any], Callable[..., Any]] = {}


def compile_enabled(device: torch.device) -> bool:
    return device.type == "cuda" and os.environ.get("MORPHEUS_COMPILE", "1") != "0"


def compiled_for(fn: Callable[..., Any], device: torch.device) -> Callable[..., Any]:
    """``fn`` compiled (dynamic shapes: point counts change every step) where that is enabled."""
    if not compile_enabled(device):
        return fn
    if fn not in _compiled:
        _compiled[fn] = torch.compile(fn, dynamic=True)
    return _compiled[fn]


def pick_device(name: str) -> torch.device:
    """``auto`` → CUDA when available, else CPU; an explicit CUDA request without CUDA fails."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(name)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeError(f"device {name!r} requested but CUDA is not available; use device=cpu or auto")
    return dev


def to_device(t: Tensor, device: torch.device | str | None, dtype: torch.dtype | None = None) -> Tensor:
    """``t`` on ``device``: a CPU tensor headed for CUDA goes through pinned memory with a
    non-blocking copy, because a copy from pageable memory makes the host wait until the GPU has
    drained its queue (a stall per random draw). The caching host allocator keeps the pinned block
    alive until the copy has run."""
    target = torch.device(device) if device is not None else t.device
    if t.device.type == "cpu" and target.type == "cuda":
        return (t if dtype is None else t.to(dtype)).pin_memory().to(target, non_blocking=True)
    return t.to(device=target, dtype=dtype)


def filled_like(value: float | tuple[float, ...] | Tensor, like: Tensor) -> Tensor:
    """``value`` (a number, a tuple of numbers or a tensor) as a tensor of ``like``'s dtype and
    device. Numbers are filled in on the device: copying a host tensor there is a sync every call."""
    if isinstance(value, Tensor):
        return value.to(like)
    if isinstance(value, int | float):
        return like.new_full((), float(value))
    return torch.stack([like.new_full((), float(v)) for v in value])
