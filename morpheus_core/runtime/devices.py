"""Which torch device a configuration's device name means, whether its kernels are compiled, and
how host-drawn random values reach it without stalling the host."""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from morpheus_core.runtime.execution import current_execution

# ``torch.compile`` of hot pure-tensor kernels (the hash-grid encode): on CUDA only — it fuses the
# gather/weight arithmetic into a few Triton kernels (DESIGN.md §7: 14 → 2 ms per 2^18 points) —
# while CPU keeps the eager code (inductor's CPU path needs a compiler and pays minutes of
# compilation for little gain). ``execution.compile=false`` (``morpheus_core.runtime.execution``, alias
# ``MORPHEUS_COMPILE=0``) turns it off (debugging, benchmarks' "before").
_compiled: dict[Callable[..., Any], Callable[..., Any]] = {}


def compile_enabled(device: torch.device) -> bool:
    """Whether ``compiled_for`` compiles on ``device``: CUDA, unless ``execution.compile`` is off."""
    return device.type == "cuda" and current_execution().compile


def compiled_for(fn: Callable[..., Any], device: torch.device) -> Callable[..., Any]:
    """``fn`` compiled (dynamic shapes: point counts change every step) where that is enabled.

    A function that torch.compile fails on (a dynamo or backend bug of the installed torch) runs
    eagerly from then on, after one warning: the results are the same, only slower."""
    if not compile_enabled(device):
        return fn
    if fn not in _compiled:
        # Donated buffers forbid a second backward through a compiled graph (retain_graph), which
        # gradient checks and the guidance's two-pass test take.
        import torch._functorch.config as functorch_config  # not an attribute until imported (torch 2.11)

        functorch_config.donated_buffer = False
        _compiled[fn] = _falls_back(fn, torch.compile(fn, dynamic=True))
    return _compiled[fn]


def _falls_back(fn: Callable[..., Any], compiled: Callable[..., Any]) -> Callable[..., Any]:
    from torch._dynamo.exc import TorchDynamoException

    def call(*args: Any) -> Any:
        try:
            return compiled(*args)
        except TorchDynamoException as exc:
            warnings.warn(f"torch.compile failed on {fn.__module__}.{fn.__qualname__}; it runs eagerly from now "
                          f"on (same results, slower): {str(exc).splitlines()[0]}", RuntimeWarning, stacklevel=2)
            _compiled[fn] = fn
            return fn(*args)

    return call


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
