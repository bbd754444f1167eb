"""Where and in which precision the priors run, and the accelerated path for frozen forwards.

Frozen networks (UNets, ControlNet, encoders) are cast to ``dtype``; the SD-family VAE stays in
float32 under float16 because its activations are known to overflow there (bfloat16 has the
range, so it is used as is). Trainable LoRA weights stay float32 and meet half-precision weights
under autocast. ``accel`` picks how the networks' forwards run: eager, replayed from CUDA graphs
captured per input shape (forward and backward; the Zero123 forward is launch-bound: DESIGN.md §7),
or ``torch.compile``.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Sequence
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass
from typing import Any, ClassVar, Generic, Literal, TypeVar

import torch
from torch import Tensor, nn
from torch.autograd.function import once_differentiable

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
        if self.dtype not in (torch.float32, *_HALF):
            raise ValueError(f"prior dtype must be float32, float16 or bfloat16, got {self.dtype}")
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


K = TypeVar("K")
V = TypeVar("V")


class LruCache(Generic[K, V]):
    """At most ``size`` entries; the least recently used one goes first. CUDA graphs hold their
    activations for as long as they live, and a batch's shapes change as its objects finish."""

    def __init__(self, size: int) -> None:
        if size < 1:
            raise ValueError(f"cache size must be >= 1, got {size}")
        self.size = size
        self._items: OrderedDict[K, V] = OrderedDict()

    def get(self, key: K) -> V | None:
        if key in self._items:
            self._items.move_to_end(key)
            return self._items[key]
        return None

    def put(self, key: K, value: V) -> V:
        self._items[key] = value
        self._items.move_to_end(key)
        while len(self._items) > self.size:
            self._items.popitem(last=False)
        return value

    def clear(self) -> None:
        self._items.clear()

    def __len__(self) -> int:
        return len(self._items)


@dataclass
class _Captured:
    """One input signature's graphs and their static buffers."""

    inputs: list[Tensor]
    output: Tensor
    forward: torch.cuda.CUDAGraph
    backward: torch.cuda.CUDAGraph | None = None
    grad_output: Tensor | None = None
    grads: tuple[Tensor | None, ...] = ()
    generation: int = 0


class GraphedCall:
    """Replays ``fn(*tensors)`` from CUDA graphs captured once per input signature.

    Without gradients, one graph of the forward. With gradients (an argument requires them, or
    ``params`` are given), a forward and a backward graph: gradients reach the arguments that
    require them and ``params``, which ``fn`` reads where they are (an optimiser's in-place updates
    are seen). ``fn`` must not sync with the host or draw random numbers. Inputs are copied into
    static buffers, outputs and gradients out of them, so callers see ordinary tensors; a backward
    whose saved activations a later forward of the same signature has overwritten raises instead
    of returning wrong gradients. Capture happens on first use of a signature, after two warm-up
    runs on a side stream (CUDA graphs require it). Forward-only graphs share one memory pool (their
    activations die within a replay); each graph with a backward has its own, so no other replay
    can overwrite the activations it saved.

    On the H200 a capture with gradients failed (``cudaErrorStreamCaptureImplicit``) while an
    *eager* autograd graph through ``params`` was still alive, whose gradient accumulators belong
    to the default stream; a live graph of an earlier replay did not hurt. The optimising loop
    drops each step's graph before the next step, where new signatures appear.
    """

    captures: ClassVar[int] = 0
    """Graphs captured in this process (all instances): steady-state steps should add none."""

    def __init__(self, fn: Callable[..., Tensor], params: Sequence[Tensor] = (), keep: int = 4) -> None:
        self.fn = fn
        self.params = tuple(params)
        self.graphs: LruCache[tuple, _Captured] = LruCache(keep)
        self.pool = None  # shared by the forward-only graphs: their activations die within a replay

    def __call__(self, *args: Tensor) -> Tensor:
        grad = torch.is_grad_enabled() and any(t.requires_grad for t in (*args, *self.params))
        key = (grad, torch.is_autocast_enabled(args[0].device.type),
               *((tuple(a.shape), a.stride(), a.dtype, a.device, a.requires_grad) for a in args))
        cap = self.graphs.get(key)
        if cap is None:
            cap = self.graphs.put(key, self._capture(args, grad))
        if grad:
            return _Replay.apply(cap, len(args), *args, *self.params)
        _load(cap, args)
        cap.forward.replay()
        return cap.output.clone()

    def _capture(self, args: tuple[Tensor, ...], grad: bool) -> _Captured:
        GraphedCall.captures += 1
        static = [a.detach().clone().requires_grad_(a.requires_grad and grad) for a in args]
        surface = (*static, *self.params)
        wrt = [t for t in surface if t.requires_grad] if grad else []
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side), torch.set_grad_enabled(grad):
            for _ in range(2):
                out = self.fn(*static)
                if wrt:
                    torch.autograd.grad(out, wrt, torch.ones_like(out), allow_unused=True)
        torch.cuda.current_stream().wait_stream(side)
        if not grad and self.pool is None:
            self.pool = torch.cuda.graph_pool_handle()
        # A backward graph reads activations saved by its forward replay: no other graph may reuse them.
        pool = torch.cuda.graph_pool_handle() if grad else self.pool
        forward = torch.cuda.CUDAGraph()
        with torch.set_grad_enabled(grad), torch.cuda.graph(forward, pool=pool):
            out = self.fn(*static)
        cap = _Captured(static, out, forward, grads=(None,) * len(surface))
        if wrt and out.requires_grad:
            cap.grad_output = torch.empty_like(out)
            cap.backward = torch.cuda.CUDAGraph()
            with torch.cuda.graph(cap.backward, pool=pool):
                found = iter(torch.autograd.grad(out, wrt, cap.grad_output, allow_unused=True))
            cap.grads = tuple(next(found) if t.requires_grad else None for t in surface)
        return cap


def _load(cap: _Captured, args: Sequence[Tensor]) -> None:
    for buf, a in zip(cap.inputs, args, strict=True):
        if buf.data_ptr() != a.data_ptr():
            buf.copy_(a)


class _Replay(torch.autograd.Function):
    """A graphed call in the autograd graph: forward and backward are replays."""

    @staticmethod
    def forward(ctx: Any, cap: _Captured, n_args: int, *inputs: Tensor) -> Tensor:
        _load(cap, inputs[:n_args])
        cap.forward.replay()
        cap.generation += 1
        ctx.cap, ctx.generation = cap, cap.generation
        return cap.output.detach().clone()

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, grad_output: Tensor) -> tuple[Tensor | None, ...]:
        cap: _Captured = ctx.cap
        if cap.backward is None or cap.grad_output is None:
            return (None, None, *(None for _ in cap.grads))
        if ctx.generation != cap.generation:
            raise RuntimeError("a graphed call was replayed again before the backward of an earlier call "
                               "with the same input shapes: its saved activations are gone; run backward "
                               "after each call, or use accel='eager'")
        cap.grad_output.copy_(grad_output)
        cap.backward.replay()
        return (None, None, *(None if g is None else g.clone() for g in cap.grads))
