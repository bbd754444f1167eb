"""Which torch device a configuration's device name means, and whether its kernels are compiled."""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

import torch

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
