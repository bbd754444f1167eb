"""Where and in which precision the priors run, and the accelerated path for frozen forwards.

Frozen networks (UNets, ControlNet, encoders) are cast to ``dtype``; the SD-family VAE stays in
float32 under float16 because its activations are known to overflow there (bfloat16 has the
range, so it is used as is; ``vae_dtype`` sets it apart). The official code runs it in float16.
On the H200 a bfloat16 VAE did not change the stages' step times beyond the run-to-run noise
(``benchmarks/results/vae_precision_h200.md``), so float32 stays the default.
Trainable LoRA weights stay float32 and meet half-precision weights
under autocast. ``accel`` picks how the networks' forwards run: eager, replayed from CUDA graphs
captured per input shape (forward and backward; the Zero123 forward is launch-bound: DESIGN.md §7),
or ``torch.compile``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor, nn

from morpheus_core.runtime.cuda_graphs import GraphedCall

Accel = Literal["eager", "cudagraph", "compile"]
_HALF = (torch.float16, torch.bfloat16)


@dataclass(frozen=True)
class PriorRuntime:
    """Device, precision and acceleration of the priors (one value shared by all of them)."""

    device: str = "cpu"
    dtype: torch.dtype = torch.float32
    vae_dtype: torch.dtype | None = None
    channels_last: bool = False
    accel: Accel = "eager"

    def __post_init__(self) -> None:
        for name, dtype in (("dtype", self.dtype), ("vae_dtype", self.vae_dtype or torch.float32)):
            if dtype not in (torch.float32, *_HALF):
                raise ValueError(f"prior {name} must be float32, float16 or bfloat16, got {dtype}")
        if self.accel not in ("eager", "cudagraph", "compile"):
            raise ValueError(f"accel must be eager, cudagraph or compile, got {self.accel!r}")
        if self.accel == "cudagraph" and torch.device(self.device).type != "cuda":
            raise ValueError("accel='cudagraph' needs a CUDA device")

    @classmethod
    def for_device(cls, device: str | torch.device, accel: Accel = "eager") -> PriorRuntime:
        """float16 + channels_last on CUDA (the paper runs fp16), float32 eager elsewhere."""
        dev = torch.device(device)
        if dev.type == "cuda":
            return cls(str(dev), torch.float16, channels_last=True, accel=accel)
        return cls(str(dev))

    @property
    def torch_device(self) -> torch.device:
        return torch.device(self.device)

    @property
    def vae_precision(self) -> torch.dtype:
        """``vae_dtype`` where set; else the priors' dtype, except float32 under float16 (see the module doc)."""
        if self.vae_dtype is not None:
            return self.vae_dtype
        return torch.float32 if self.dtype == torch.float16 else self.dtype

    def place(self, module: nn.Module, dtype: torch.dtype | None = None) -> nn.Module:
        """Move a frozen network to the device and precision, frozen and in eval mode."""
        module = module.to(device=self.torch_device)
        target = dtype or self.dtype
        if any(p.dtype != target for p in module.parameters()):  # diffusers warns on every .to(dtype)
            module = module.to(dtype=target)
        if self.channels_last:
            module = module.to(memory_format=torch.channels_last)
        module.requires_grad_(False)
        return module.eval()

    def autocast(self, cache: bool = True) -> AbstractContextManager:
        """Mixed precision for forwards that combine half weights with float32 (LoRA) weights.
        ``cache=False`` inside a captured graph: autocast's cast cache must not outlive a capture."""
        if self.dtype == torch.float32:
            return nullcontext()
        return torch.autocast(self.torch_device.type, dtype=self.dtype, cache_enabled=cache)

    def accelerate(self, fn: Callable[..., Tensor], params: Sequence[Tensor] = ()) -> Callable[..., Tensor]:
        """Wrap a forward of tensors only (shapes fixed per call) in the chosen path. ``params``:
        the weights ``fn`` reads that take gradients (LoRA adapters); a frozen network has none."""
        if self.accel == "cudagraph":
            return GraphedCall(fn, params)
        if self.accel == "compile":
            return torch.compile(fn, dynamic=False)
        return fn
