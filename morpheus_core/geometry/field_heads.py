"""The NeRF field's density and albedo heads evaluated together, fused on CUDA.

``evaluate_heads`` runs both MLPs on the same hash-grid features. On CUDA (where Triton imports)
that is ``mlp_triton``'s two kernels, forward and backward; elsewhere, and for inputs those
kernels do not take, the ``nn.Sequential`` modules themselves (the CPU path and the reference).
``execution.field_mlp`` (``morpheus_core.runtime.execution``, alias ``MORPHEUS_FIELD_MLP``) picks, like
``execution.hashgrid`` (``triton_support.choose``): ``auto`` (the kernels on CUDA; the default),
``triton`` (insist) or ``eager`` (the modules everywhere).
The kernels' TF32 products were checked against the fp32 modules on all 8 synthetic scenes × 3
seeds (``benchmarks/results/heads_quality_h200.md``: every scene inside the seed spread). The
parameters stay the modules' own, so checkpoints, optimisers and parameter groups do not see which
path ran.
"""

from __future__ import annotations

from types import ModuleType
from typing import Any

import torch
from torch import Tensor, nn

from morpheus_core.runtime.execution import current_execution
from morpheus_core.runtime.triton_support import choose


def head_parameters(mlp: nn.Module) -> list[Tensor] | None:
    """(w1, b1, w2, b2, w3, b3) of a Linear-ReLU-Linear-ReLU-Linear ``nn.Sequential``, else None."""
    layers = list(mlp.children()) if isinstance(mlp, nn.Sequential) else []
    kinds = [type(layer) for layer in layers]
    if kinds != [nn.Linear, nn.ReLU, nn.Linear, nn.ReLU, nn.Linear]:
        return None
    params: list[Tensor] = []
    for linear in layers[::2]:
        if linear.bias is None:
            return None
        params += [linear.weight, linear.bias]
    return params


def _kernels(feats: Tensor, mlps: list[nn.Module]) -> tuple[ModuleType, list[list[Tensor]]] | None:
    """The kernel module and the heads' parameters when the kernels take these heads, else None.
    The parameters are gathered only once ``choose`` asks: the CPU's path does no extra work."""
    heads: list[list[Tensor] | None] = []

    def load() -> ModuleType:
        from morpheus_core.geometry import mlp_triton

        return mlp_triton

    def supported() -> bool:
        heads.extend(head_parameters(m) for m in mlps)
        return all(h is not None for h in heads) and load().supports(feats, heads)  # type: ignore[arg-type]

    kernels = choose(current_execution().field_mlp, "execution.field_mlp", feats.device, supported, load, "field-MLP")
    return (kernels, heads) if kernels is not None else None  # type: ignore[return-value]


class _FusedHeads(torch.autograd.Function):
    """Both heads through ``mlp_triton``; an unused output's head costs nothing in the backward."""

    @staticmethod
    def forward(ctx: Any, feats: Tensor, kernels: ModuleType, with_albedo: bool,  # type: ignore[override]
                *params: Tensor) -> tuple[Tensor, ...]:
        density, albedo = list(params[:6]), (list(params[6:]) if with_albedo else None)
        ctx.kernels, ctx.with_albedo = kernels, with_albedo
        ctx.save_for_backward(feats, *params)
        ctx.set_materialize_grads(False)
        raw_density, raw_albedo = kernels.heads_forward(feats, density, albedo)
        return (raw_density, raw_albedo) if raw_albedo is not None else (raw_density,)

    @staticmethod
    def backward(ctx: Any, grad_density: Tensor | None, grad_albedo: Tensor | None = None) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        feats, *params = ctx.saved_tensors
        density, albedo = params[:6], (params[6:] if ctx.with_albedo else None)
        grad_x, grads_d, grads_a = ctx.kernels.heads_backward(
            feats, density, albedo, grad_density, grad_albedo, bool(ctx.needs_input_grad[0]))
        grads = list(grads_d or [None] * 6) + (list(grads_a or [None] * 6) if ctx.with_albedo else [])
        wanted = ctx.needs_input_grad[3:]
        return (grad_x, None, None, *[g if w else None for g, w in zip(grads, wanted, strict=True)])


def evaluate_heads(feats: Tensor, density_mlp: nn.Module, albedo_mlp: nn.Module | None) -> tuple[Tensor, Tensor | None]:
    """``(density_mlp(feats), albedo_mlp(feats))``, the second None when ``albedo_mlp`` is."""
    chosen = _kernels(feats, [density_mlp] + ([albedo_mlp] if albedo_mlp is not None else []))
    if chosen is None:
        return density_mlp(feats), (albedo_mlp(feats) if albedo_mlp is not None else None)
    kernels, heads = chosen
    out = _FusedHeads.apply(feats, kernels, albedo_mlp is not None, *[p for head in heads for p in head])
    return out[0], (out[1] if albedo_mlp is not None else None)
