"""VSD's fine-tuned counterpart ε_φ: one peft LoRA per object on a prior's own UNet.

- peft LoRA r = 4 on to_q / to_k / to_v / to_out.0, α = r (scale 1), B initialised to zero so
  ε_φ starts equal to the prior; Adam, lr 1e-4 (ProlificDreamer / the paper).
- No second UNet: the frozen prediction is the same UNet with its adapters off, which is exactly
  adapter scale 0 (a test checks both against a UNet that never had adapters).
- Many objects in one batch: adapters are peft's (injection, state dicts), but the forward is
  row-batched here — a hook on every LoRA layer adds ``scale · B_k A_k x`` with each row's own
  object k, gathered in one batched matmul. peft's own mixed-adapter path loops over objects per
  layer (and is inference-only); a per-object UNet loop would cost one full forward per object.
- The fine-tuning loss is the guidance's ``finetune_loss`` (ε-MSE at t ~ U[0, T) on the detached
  rendered latents); ``step()`` applies each object's Adam.
- Checkpoints: ``save``/``load`` write one safetensors file per object, atomically
  (``morpheus_core.runtime.atomic_io``).
"""

from __future__ import annotations

import hashlib
import warnings
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from morpheus_core.priors.runtime import PriorRuntime
from morpheus_core.runtime.atomic_io import atomic_write
from morpheus_core.runtime.cuda_graphs import LruCache
from morpheus_core.runtime.device_skip import nonfinite, step_or_skip


@dataclass(frozen=True)
class LoraSettings:
    """A LoRA adapter on a prior's attention projections and the Adam that trains it."""

    rank: int = 4
    """Rank of the low-rank update of each adapted layer."""
    alpha: float = 4.0
    """Scale of the update: ``alpha / rank`` multiplies it (alpha = rank: scale 1)."""
    target_modules: tuple[str, ...] = ("to_q", "to_k", "to_v", "to_out.0")
    """Names of the attention projections that get an adapter (diffusers' attention layers)."""
    lr: float = 1e-4
    """Adam learning rate of the adapter (ProlificDreamer and the paper: 1e-4)."""
    betas: tuple[float, float] = (0.9, 0.999)
    """Adam's moment decay rates."""

    def __post_init__(self) -> None:
        if self.rank < 1 or not self.alpha > 0 or not self.lr > 0:
            raise ValueError(f"invalid LoRA settings {self}")

    def metadata(self) -> dict[str, str]:
        return {"rank": str(self.rank), "alpha": repr(self.alpha), "target_modules": ",".join(self.target_modules)}


class LoraHost(Protocol):
    """A UNet prior the LoRA can ride on (``Zero123Prior``, ``Image2DPrior``)."""

    unet: nn.Module
    runtime: PriorRuntime

    def encode(self, images: Tensor) -> Tensor: ...

    def decode(self, latents: Tensor) -> Tensor: ...

    def predict_noise(self, noisy: Tensor, t: Tensor, condition: Any, cfg_scale: float,
                      lora: ObjectLoras | None = None) -> Tensor: ...


def adapter_name(object_id: str) -> str:
    """Object ids are file-derived and may hold dots; peft adapter names must not."""
    return "obj_" + hashlib.sha1(object_id.encode("utf-8")).hexdigest()[:16]


class ObjectLoras:
    """Per-object LoRA adapters on ``host.unet``; implements ``Prior`` as the VSD counterpart."""

    def __init__(self, host: LoraHost, settings: LoraSettings | None = None) -> None:
        self.host = host
        self.settings = settings or LoraSettings()
        self.unet = host.unet
        self._names: dict[str, str] = {}
        self._optimizers: dict[str, torch.optim.Optimizer] = {}
        self._layers: list[nn.Module] = []
        # Per set of rows (a step uses two: the CFG pairs and the plain rows); a batch's sets change.
        self._graphs: LruCache[tuple, tuple[tuple[int, ...], Callable[..., Tensor]]] = LruCache(4)

    # -- adapters -------------------------------------------------------------------------------

    @property
    def object_ids(self) -> tuple[str, ...]:
        return tuple(self._names)

    def add(self, object_id: str) -> None:
        from peft import LoraConfig
        from peft.tuners.lora import LoraLayer

        if object_id in self._names:
            raise ValueError(f"object {object_id!r} already has a LoRA adapter")
        s = self.settings
        config = LoraConfig(r=s.rank, lora_alpha=s.alpha, target_modules=list(s.target_modules),
                            lora_dropout=0.0, init_lora_weights=True)
        with warnings.catch_warnings():  # peft warns that a model holds several adapters: by design
            warnings.simplefilter("ignore", UserWarning)
            self.unet.add_adapter(config, adapter_name=adapter_name(object_id))
        # Off by default: every plain forward is the frozen prior; rows opt in through denoise().
        self.unet.disable_adapters()
        self._names[object_id] = adapter_name(object_id)
        self._layers = [m for m in self.unet.modules() if isinstance(m, LoraLayer)]
        self._graphs.clear()  # captured with the old layer set
        for oid in self._names:  # disable_adapters() froze every adapter; they all train
            for p in self.parameters(oid):
                p.data = p.data.float()  # Adam state and updates in float32 under a half UNet
                p.requires_grad_(True)
        self._optimizers[object_id] = torch.optim.Adam(self.parameters(object_id), lr=s.lr, betas=s.betas,
                                                       fused=True)

    def remove(self, object_id: str) -> None:
        name = self._require([object_id])[0]
        with warnings.catch_warnings():  # "active adapter deleted": none is active outside denoise()
            warnings.simplefilter("ignore", UserWarning)
            self.unet.delete_adapters(name)
        del self._names[object_id], self._optimizers[object_id]
        from peft.tuners.lora import LoraLayer

        self._layers = [m for m in self.unet.modules() if isinstance(m, LoraLayer) and m.lora_A]
        self._graphs.clear()

    def parameters(self, object_id: str) -> list[nn.Parameter]:
        return self._adapter_weights(self._require([object_id])[0])

    def _adapter_weights(self, name: str) -> list[nn.Parameter]:
        return [w for layer in self._layers for w in (layer.lora_A[name].weight, layer.lora_B[name].weight)]

    def _require(self, object_ids: Sequence[str]) -> list[str]:
        missing = [o for o in dict.fromkeys(object_ids) if o not in self._names]
        if missing:
            raise KeyError(f"no LoRA adapter for objects {missing}; call add(object_id) first")
        return [self._names[o] for o in object_ids]

    def _index(self, names: Sequence[str]) -> Tensor:
        unique = list(dict.fromkeys(names))
        return torch.tensor([unique.index(n) for n in names], device=self.host.runtime.torch_device)

    @contextmanager
    def _rows(self, names: Sequence[str], index: Tensor) -> Iterator[None]:
        """Within this block, every forward of the UNet adds row i's object adapter (``index[i]`` into
        the unique ``names``) to row i."""
        hook = _RowLora(list(dict.fromkeys(names)), index)
        handles = [layer.register_forward_hook(hook) for layer in self._layers]
        try:
            yield
        finally:
            for h in handles:
                h.remove()

    def denoise(self, fn: Callable[..., Tensor], args: tuple[Tensor, ...], object_ids: Sequence[str]) -> Tensor:
        """``fn(*args)`` (the host's UNet call) with row i's object adapter added to row i.

        On a ``cudagraph`` runtime the call, and with gradients its backward into the adapters, is
        replayed from CUDA graphs (``PriorRuntime.accelerate``) per set of rows. Eager, this call is
        launch-bound: ~4,200 small copies a texture step around the 128 adapter hooks
        (``benchmarks/results/paper_speed_h200.md``). A graph reads the adapters' weights where they
        are, so Adam's in-place updates are seen; it is captured again when an adapter's storage
        moves (``add``, or a state load that replaces it).
        """
        names = self._require(object_ids)
        runtime = self.host.runtime
        if runtime.accel != "cudagraph":
            with self._rows(names, self._index(names)), runtime.autocast():
                return fn(*args)
        key = (fn, tuple(names))
        params = [p for n in dict.fromkeys(names) for p in self._adapter_weights(n)]
        storage = tuple(p.data_ptr() for p in params)
        cached = self._graphs.get(key)
        if cached is None or cached[0] != storage:
            index = self._index(names)  # made once, outside any capture, and kept alive by the closure

            def adapted(*inputs: Tensor) -> Tensor:
                # No cast cache: it must not outlive a capture (and a replay does not run this code).
                with self._rows(names, index), runtime.autocast(cache=False):
                    return fn(*inputs)

            cached = self._graphs.put(key, (storage, runtime.accelerate(adapted, params)))
        return cached[1](*args)

    # -- Prior protocol (the VSD counterpart) ---------------------------------------------------

    def encode(self, images: Tensor) -> Tensor:
        return self.host.encode(images)

    def decode(self, latents: Tensor) -> Tensor:
        return self.host.decode(latents)

    def predict_noise(self, noisy: Tensor, t: Tensor, condition: Any, cfg_scale: float) -> Tensor:
        return self.host.predict_noise(noisy, t, condition, cfg_scale, lora=self)

    # -- optimisation ---------------------------------------------------------------------------

    def step(self, object_ids: Sequence[str] | None = None, ok: Tensor | bool = True) -> Tensor:
        """One Adam step per object (of ``object_ids``, default all) that received gradients, unless
        ``ok`` is false or the object's gradients are not finite (a half-precision overflow must not
        corrupt an adapter). Decided on the device (``morpheus_core.runtime.device_skip``); returns per object
        whether its step was skipped (a bool tensor, in order)."""
        ids = tuple(object_ids) if object_ids is not None else tuple(self._optimizers)
        self._require(ids)
        device = self.host.runtime.torch_device
        skipped = []
        for oid in ids:
            opt = self._optimizers[oid]
            grads = [p.grad for p in self.parameters(oid) if p.grad is not None]
            if not grads or ok is False:
                skipped.append(torch.full((), bool(grads), dtype=torch.bool, device=device))
            else:
                bad = nonfinite(grads, device)
                bad = bad if ok is True else bad | ~ok  # type: ignore[operator]
                step_or_skip(opt, bad)
                skipped.append(bad)
            opt.zero_grad(set_to_none=True)
        return torch.stack(skipped) if skipped else torch.zeros(0, dtype=torch.bool, device=device)

    # -- checkpoints ----------------------------------------------------------------------------

    def state_dict(self, object_id: str) -> dict[str, Tensor]:
        from peft.utils import get_peft_model_state_dict

        name = self._require([object_id])[0]
        state = get_peft_model_state_dict(self.unet, adapter_name=name)
        return {k: v.detach().to("cpu", torch.float32).contiguous() for k, v in state.items()}

    def load_state_dict(self, object_id: str, state: dict[str, Tensor]) -> None:
        from peft.utils import set_peft_model_state_dict

        expected = set(self.state_dict(object_id))
        if set(state) != expected:
            diff = sorted(set(state) ^ expected)[:5]
            raise KeyError(f"LoRA state for {object_id!r} does not match this UNet's adapter (e.g. {diff})")
        set_peft_model_state_dict(self.unet, state, adapter_name=self._names[object_id])

    def optimizer_state_dict(self, object_id: str) -> dict[str, Any]:
        """The object's Adam state, so a resumed run continues the same update sequence."""
        self._require([object_id])
        return self._optimizers[object_id].state_dict()

    def load_optimizer_state_dict(self, object_id: str, state: dict[str, Any]) -> None:
        self._require([object_id])
        self._optimizers[object_id].load_state_dict(state)

    def save(self, object_id: str, path: Path) -> Path:
        """Write the object's adapter as safetensors, atomically."""
        from safetensors.torch import save_file

        metadata = {"object_id": object_id, **self.settings.metadata()}
        return atomic_write(Path(path), lambda tmp: save_file(self.state_dict(object_id), str(tmp), metadata=metadata))

    def load(self, object_id: str, path: Path) -> None:
        """Restore an adapter saved by ``save`` (adding it if needed); optimiser state restarts."""
        from safetensors import safe_open
        from safetensors.torch import load_file

        with safe_open(str(path), framework="pt") as fh:
            meta = fh.metadata() or {}
        want = self.settings.metadata()
        if {k: meta.get(k) for k in want} != want:
            raise ValueError(f"{path} holds a LoRA with {meta}, these settings need {want}")
        if object_id not in self._names:
            self.add(object_id)
        self.load_state_dict(object_id, load_file(str(path)))


class _RowLora:
    """Forward hook on one peft LoRA layer: output + scale · B_k(A_k x) with k the row's object."""

    def __init__(self, names: list[str], index: Tensor) -> None:
        self.names = names
        self.index = index

    def __call__(self, layer: nn.Module, args: tuple[Any, ...], output: Tensor) -> Tensor:
        x = args[0]
        scale = layer.scaling[self.names[0]]  # one LoraSettings → the same α/r for every object
        a_w = [layer.lora_A[n].weight for n in self.names]
        b_w = [layer.lora_B[n].weight for n in self.names]
        x = x.to(a_w[0].dtype)
        if len(self.names) == 1:
            delta = F.linear(F.linear(x, a_w[0]), b_w[0])
        else:
            flat = x.reshape(x.shape[0], -1, x.shape[-1])
            a = torch.stack(a_w)[self.index]  # B×r×in
            b = torch.stack(b_w)[self.index]  # B×out×r
            delta = torch.bmm(torch.bmm(flat, a.transpose(1, 2)), b.transpose(1, 2)).reshape(*x.shape[:-1], -1)
        return output + (scale * delta).to(output.dtype)
