"""Fixed-size sample buffers for the volume renderer's training renders (``SampleBudget``) and
the field evaluation they run, eager or replayed from CUDA graphs (``field_values``)."""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor, nn

from morpheus_core.geometry.nerf import RadianceField
from morpheus_core.runtime.cuda_graphs import GraphedCall

FieldValues = Callable[[Tensor], tuple[Tensor, ...]]
"""Points (N, 3) → ``field_values``."""


def field_values(field: RadianceField, points: Tensor, with_normals: bool, chunk: int) -> tuple[Tensor, ...]:
    """The field at ``points`` (N, 3), evaluated ``chunk`` points at a time: density (N,), albedo
    (N, 3) and, ``with_normals``, normals (N, 3), in ``points``' dtype. Tensors only, so that a
    CUDA graph can stand in for it (``SampleBudget.evaluator``)."""
    samples = [field.query(x, with_normals) for x in points.split(chunk)]
    values = [torch.cat([s.density for s in samples]), torch.cat([s.albedo for s in samples])]
    if with_normals:
        values.append(torch.cat([s.normal for s in samples]))  # type: ignore[misc]
    return tuple(v.to(points.dtype) for v in values)


class SampleBudget:
    """Fixed-size sample buffers for a task's training renders, one per named gather.

    A padded gather evaluates the field on exactly ``capacity`` samples whatever the occupancy grid
    keeps, so no step has to ask the host how many there are. Kept samples are taken in sample
    order (every ray's first sample, then every ray's second, …), so when more are kept than fit
    the ones dropped are the deepest, behind what the ray has most likely hit already; how many
    were dropped is counted on the device. ``adapt`` (one host read, every few steps: the NeRF
    stage calls it at each occupancy refresh) resizes a buffer to ``headroom`` × the most samples
    it was asked for since, rounded up to ``quantum``, once that peak leaves ``hold`` × the peak the
    buffer was sized for (capacity / headroom); a buffer's first gather sizes it the same way from
    its own count. ``hold`` keeps shapes put while the occupancy drifts a little, because
    ``graphed`` buffers are CUDA graphs (one per buffer: the field's forward and backward,
    ``evaluator``) and every new size is a new capture.
    """

    def __init__(self, headroom: float = 1.25, quantum: int = 1 << 16, hold: tuple[float, float] = (0.75, 1.125),
                 graphed: bool = False) -> None:
        if not headroom >= 1.0 or quantum < 1:
            raise ValueError(f"headroom must be ≥ 1 and quantum ≥ 1, got {headroom} and {quantum}")
        if not 0.0 <= hold[0] <= 1.0 <= hold[1]:
            raise ValueError(f"hold must be (low, high) with 0 ≤ low ≤ 1 ≤ high, got {hold}")
        self.headroom, self.quantum, self.hold, self.graphed = headroom, quantum, hold, graphed
        self.capacity: dict[str, int] = {}
        self.resizes = 0
        """Buffers resized by ``adapt`` since the budget was made (for graphed buffers: recaptures)."""
        self._peak: dict[str, Tensor] = {}
        self._dropped: dict[str, Tensor] = {}
        self._graphs: dict[tuple, GraphedCall] = {}

    def evaluator(self, name: str, field: RadianceField, with_normals: bool, chunk: int) -> FieldValues:
        """How buffer ``name`` evaluates ``field`` (``field_values``): eagerly, or (``graphed``)
        replayed from a CUDA graph of the forward and the backward into the field's parameters.
        One graph per buffer, kept for one size: a graph holds its activations until the next
        replay, and each buffer's are needed until the step's backward."""
        def values(x: Tensor) -> tuple[Tensor, ...]:
            return field_values(field, x, with_normals, chunk)

        if not self.graphed:
            return values
        key = (name, id(field), with_normals, chunk)
        if key not in self._graphs:
            if not isinstance(field, nn.Module):  # the graph's backward reaches only parameters it was given
                raise TypeError(f"graphed sample buffers need a field that is an nn.Module, got {type(field).__name__}")
            self._graphs[key] = GraphedCall(values, list(field.parameters()), keep=1)
        return self._graphs[key]

    def gather(self, name: str, keep: Tensor) -> tuple[Tensor, Tensor]:
        """Flat indices (into ``keep``, (R, S) ray-major) of up to ``capacity`` kept samples, padded
        with ``keep.numel()`` (a slot whose result is discarded), and the kept count (device). A
        buffer's first gather sizes it from its count (one host read, once)."""
        r, s = keep.shape
        n = r * s
        order = keep.t().reshape(-1)
        pos = torch.cumsum(order, 0) - 1
        count = pos[-1] + 1
        if name not in self.capacity:  # a buffer of every sample would be 4× the memory, and slow
            self.capacity[name] = self._size(int(count))
        cap = min(self.capacity[name], n)
        slot = torch.where(order & (pos < cap), pos, cap)
        flat = torch.arange(n, device=keep.device).reshape(r, s).t().reshape(-1)
        index = torch.full((cap + 1,), n, dtype=torch.long, device=keep.device).scatter_(0, slot, flat)[:cap]
        zero = torch.zeros((), dtype=count.dtype, device=keep.device)
        self._peak[name] = torch.maximum(self._peak.get(name, zero), count)
        self._dropped[name] = self._dropped.get(name, zero) + (count - cap).clamp_min(0)
        return index, count

    def _size(self, peak: int) -> int:
        return max(self.quantum, math.ceil(peak * self.headroom / self.quantum) * self.quantum)

    def _resized(self, capacity: int, peak: int) -> int:
        sized_for = capacity / self.headroom
        held = self.hold[0] * sized_for <= peak <= self.hold[1] * sized_for
        return capacity if held else self._size(peak)

    def dropped(self) -> Tensor | None:
        """Samples dropped for want of room, summed over the buffers since the last ``adapt`` (device)."""
        return torch.stack(list(self._dropped.values())).sum() if self._dropped else None

    def adapt(self) -> dict[str, int]:
        """Resize every buffer from the peak count since the last call (one host read); returns and
        forgets the samples dropped meanwhile, per buffer."""
        if not self._peak:
            return {}
        names = list(self._peak)
        values = torch.stack([self._peak[k] for k in names] + [self._dropped[k] for k in names]).tolist()
        for name, peak in zip(names, values[:len(names)], strict=True):
            size = self._resized(self.capacity[name], peak)
            self.resizes += size != self.capacity[name]
            self.capacity[name] = size
        dropped = dict(zip(names, (int(v) for v in values[len(names):]), strict=True))
        self._peak.clear()
        self._dropped.clear()
        return dropped
