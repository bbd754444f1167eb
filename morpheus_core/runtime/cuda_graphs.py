"""CUDA graphs for forwards (and their backwards) of fixed-shape tensor functions.

``GraphedCall`` replays a function from graphs captured once per input signature; the priors
(``PriorRuntime.accelerate``) and the NeRF stage's field queries on padded sample buffers
(``morpheus_core.render.volume.SampleBudget``) use it. ``LruCache`` bounds how many signatures
stay captured, because each graph holds its activations for as long as it lives.
"""

from __future__ import annotations

import weakref
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Generic, TypeVar

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

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
    outputs: tuple[Tensor, ...]
    single: bool
    """``fn`` returned one tensor (not a tuple of them)."""
    forward: torch.cuda.CUDAGraph
    backward: torch.cuda.CUDAGraph | None = None
    grad_outputs: tuple[Tensor | None, ...] = ()
    """Static buffers of the incoming gradients, one per output that takes one."""
    grads: tuple[Tensor | None, ...] = ()
    generation: int = 0

    def result(self, values: tuple[Tensor, ...]) -> Tensor | tuple[Tensor, ...]:
        return values[0] if self.single else values


class GraphedCall:
    """Replays ``fn(*tensors)`` (a tensor or a tuple of tensors) from CUDA graphs captured once per
    input signature.

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

    def __init__(self, fn: Callable[..., Tensor | tuple[Tensor, ...]], params: Sequence[Tensor] = (),
                 keep: int = 4) -> None:
        self.fn = fn
        self.params = tuple(params)
        self.graphs: LruCache[tuple, _Captured] = LruCache(keep)
        self.pool = None  # shared by the forward-only graphs: their activations die within a replay
        _LIVE.add(self)

    def release(self) -> None:
        """Drop every captured graph (and so its memory); the next call captures again."""
        self.graphs.clear()
        self.pool = None

    def __call__(self, *args: Tensor) -> Any:
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
        return cap.result(tuple(o.clone() for o in cap.outputs))

    def _capture(self, args: tuple[Tensor, ...], grad: bool) -> _Captured:
        GraphedCall.captures += 1
        static = [a.detach().clone().requires_grad_(a.requires_grad and grad) for a in args]
        surface = (*static, *self.params)
        wrt = [t for t in surface if t.requires_grad] if grad else []
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side), torch.set_grad_enabled(grad):
            for _ in range(2):
                outs = _as_tuple(self.fn(*static))
                taking = [o for o in outs if o.requires_grad]
                if wrt and taking:
                    torch.autograd.grad(taking, wrt, [torch.ones_like(o) for o in taking], allow_unused=True)
        torch.cuda.current_stream().wait_stream(side)
        if not grad and self.pool is None:
            self.pool = torch.cuda.graph_pool_handle()
        # A backward graph reads activations saved by its forward replay: no other graph may reuse them.
        pool = torch.cuda.graph_pool_handle() if grad else self.pool
        forward = torch.cuda.CUDAGraph()
        with torch.set_grad_enabled(grad), torch.cuda.graph(forward, pool=pool):
            out = self.fn(*static)
        outs = _as_tuple(out)
        cap = _Captured(static, outs, isinstance(out, Tensor), forward, grads=(None,) * len(surface))
        taking = [o for o in outs if o.requires_grad]
        if wrt and taking:
            cap.grad_outputs = tuple(torch.empty_like(o) if o.requires_grad else None for o in outs)
            cap.backward = torch.cuda.CUDAGraph()
            with torch.cuda.graph(cap.backward, pool=pool):
                found = iter(torch.autograd.grad(taking, wrt, [g for g in cap.grad_outputs if g is not None],
                                                 allow_unused=True))
            cap.grads = tuple(next(found) if t.requires_grad else None for t in surface)
        return cap


def _as_tuple(out: Tensor | tuple[Tensor, ...]) -> tuple[Tensor, ...]:
    return (out,) if isinstance(out, Tensor) else tuple(out)


_LIVE: weakref.WeakSet[GraphedCall] = weakref.WeakSet()


def release_graphs() -> None:
    """Drop the graphs of every ``GraphedCall`` in the process and return their memory to the
    device. A stage ends with this: the next one calls with other shapes, and the graphs the earlier
    stages kept ran the texture stage at 16 objects out of memory (H200)."""
    for call in list(_LIVE):
        call.release()
    if torch.cuda.is_initialized():
        torch.cuda.empty_cache()


def _load(cap: _Captured, args: Sequence[Tensor]) -> None:
    for buf, a in zip(cap.inputs, args, strict=True):
        if buf.data_ptr() != a.data_ptr():
            buf.copy_(a)


class _Replay(torch.autograd.Function):
    """A graphed call in the autograd graph: forward and backward are replays."""

    @staticmethod
    def forward(ctx: Any, cap: _Captured, n_args: int, *inputs: Tensor) -> Any:
        _load(cap, inputs[:n_args])
        cap.forward.replay()
        cap.generation += 1
        ctx.cap, ctx.generation = cap, cap.generation
        return cap.result(tuple(o.detach().clone() for o in cap.outputs))

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, *grad_outputs: Tensor) -> tuple[Tensor | None, ...]:
        cap: _Captured = ctx.cap
        if cap.backward is None:
            return (None, None, *(None for _ in cap.grads))
        if ctx.generation != cap.generation:
            raise RuntimeError("a graphed call was replayed again before the backward of an earlier call "
                               "with the same input shapes: its saved activations are gone; run backward "
                               "after each call, or use accel='eager'")
        for buf, g in zip(cap.grad_outputs, grad_outputs, strict=True):
            if buf is not None:  # an output the caller did not use arrives as zeros (materialised)
                buf.copy_(g)
        cap.backward.replay()
        return (None, None, *(None if g is None else g.clone() for g in cap.grads))
