"""Unified hybrid guidance of Algorithm 1: N priors × M band filters, each prior SDS or VSD.

One call returns a surrogate loss whose gradient with respect to the renders is exactly the
paper's Eq. (6) (Proposition 3), per step:

    prior guidance      Σ_n Σ_m k_nm · λc · w(t) · V Λ_nm Vᵀ (ε_n − ε_φn)     into the novel views
    reference guidance  Σ_n Σ_m k_nm · (1 − λc)/σ² · ‖Λ_nm (Vᵀx_ref − Vᵀy)‖² / (C·H·W)  on the reference view

where ε_φn is the sampled noise ε for SDS and the fine-tuned counterpart's prediction for VSD.
Both are averaged over the batch (the expectation over cameras). The reductions are the official
code's (``morpheus_core.guidance.loss_balance``): the prior term is summed over the prior's space, the
reference term is a mean over its C·H·W elements; the paper's λc only means what it says under them.
The prior term is applied in each prior's own space (its ``encode`` of the render, e.g. VAE
latents) and flows back through the encoder; the reference term acts on the RGB reference render.
VSD, Magic123, Morpheus3D and every ablation of the paper are configurations of this one function (see ``configs``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import torch
from torch import Tensor

from morpheus_core.guidance.diffusion import NoiseSchedule, TimestepRange, Weighting, sample_timesteps, work_dtype
from morpheus_core.guidance.frequency import BandMask, filter_residual
from morpheus_core.guidance.loss_balance import reference_loss
from morpheus_core.guidance.prior_protocol import Prior
from morpheus_core.runtime.devices import to_device

Mode = Literal["sds", "vsd"]


class NonFiniteInputError(ValueError):
    """A render or reference handed to the guidance holds NaN or Inf."""


@dataclass(frozen=True)
class BandWeight:
    """One (Λ_n^m, k_n^m) pair of a prior term."""

    band: BandMask
    k: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.k) and self.k >= 0.0):
            raise ValueError(f"filter weight k must be finite and ≥ 0, got {self.k}")


@dataclass(frozen=True)
class PriorTerm:
    """Prior n of Algorithm 1: which prior, SDS or VSD, its CFG scales, t range and filters."""

    prior: str
    mode: Mode
    filters: tuple[BandWeight, ...]
    cfg_scale: float = 1.0
    finetuned_cfg_scale: float = 1.0
    weighting: Weighting = "one_minus_alpha_bar"
    t_range: TimestepRange = field(default_factory=TimestepRange)
    # The VSD counterpart is trained with the standard ε-MSE at t ~ U[0, T).
    finetune_t_range: TimestepRange = field(default_factory=lambda: TimestepRange(0.0, 1.0))

    def __post_init__(self) -> None:
        if self.mode not in ("sds", "vsd"):
            raise ValueError(f"prior term mode must be 'sds' or 'vsd', got {self.mode!r}")
        if not self.filters:
            raise ValueError(f"prior term {self.prior!r} needs at least one (band, k) filter")
        if not (math.isfinite(self.cfg_scale) and math.isfinite(self.finetuned_cfg_scale)):
            raise ValueError("CFG scales must be finite")

    @property
    def is_active(self) -> bool:
        """False when every filter has k = 0 or a null band: the term contributes nothing, so
        its prior forward (and VSD fine-tuning) is skipped."""
        return any(f.k > 0.0 and f.band.kind != "null" for f in self.filters)


@dataclass(frozen=True)
class GuidanceConfig:
    """λc, σ and the prior terms; ``grad_clip`` clamps each element of the prior gradient."""

    terms: tuple[PriorTerm, ...]
    lambda_c: float = 5e-4
    sigma: float = 1.0
    grad_clip: float | None = None
    check_inputs: bool = True

    def __post_init__(self) -> None:
        if not self.terms:
            raise ValueError("guidance needs at least one prior term")
        if not (0.0 <= self.lambda_c <= 1.0):
            raise ValueError(f"lambda_c must lie in [0, 1], got {self.lambda_c}")
        if not (math.isfinite(self.sigma) and self.sigma > 0.0):
            raise ValueError(f"sigma must be finite and > 0, got {self.sigma}")
        if self.grad_clip is not None and not self.grad_clip > 0.0:
            raise ValueError(f"grad_clip must be > 0 when set, got {self.grad_clip}")

    @property
    def prior_names(self) -> tuple[str, ...]:
        return tuple(dict.fromkeys(t.prior for t in self.terms))

    @property
    def needs_finetuned(self) -> tuple[str, ...]:
        return tuple(dict.fromkeys(t.prior for t in self.terms if t.mode == "vsd"))


@dataclass
class PriorBinding:
    """The runtime objects behind a prior name: the frozen prior, its VSD counterpart (a prior
    with trainable parameters, e.g. a LoRA copy) and this step's condition (camera, edges…)."""

    prior: Prior
    finetuned: Prior | None = None
    condition: Any = None


@dataclass(frozen=True)
class TermDraw:
    """The random draws of one term for one step; sampled when not given (tests pass them)."""

    t: Tensor
    noise: Tensor
    finetune_t: Tensor | None = None
    finetune_noise: Tensor | None = None


@dataclass
class GuidanceOutput:
    """``loss`` drives the 3D parameters θ; ``finetune_loss`` drives the VSD counterparts φ.

    They are independent (stop-gradients in between), so one ``(loss + finetune_loss).backward()``
    is correct. ``stats`` holds detached tensors so reading them is the caller's choice of sync;
    the ``…/nonfinite`` entries count NaN/Inf values a prior returned (zeroed in the gradient).
    """

    loss: Tensor
    finetune_loss: Tensor
    stats: dict[str, Tensor]

    @property
    def nonfinite_prior_values(self) -> Tensor:
        counts = [v for k, v in self.stats.items() if k.endswith("/nonfinite")]
        return torch.stack(counts).sum() if counts else self.loss.new_zeros((), dtype=torch.int64)


class _InjectGradient(torch.autograd.Function):
    """Surrogate 0.5‖x − sg(x − g)‖²: value 0.5‖g‖², gradient g. Written as a function so a
    non-finite x can never turn the value into NaN (x − x is NaN for x = NaN)."""

    @staticmethod
    def forward(ctx: Any, x: Tensor, g: Tensor) -> Tensor:
        ctx.save_for_backward(g)
        ctx.x_dtype = x.dtype
        return (0.5 * g.double().pow(2).sum()).clamp(max=torch.finfo(torch.float32).max).to(g.dtype)

    @staticmethod
    def backward(ctx: Any, grad_out: Tensor) -> tuple[Tensor, None]:
        (g,) = ctx.saved_tensors
        return (g * grad_out).to(ctx.x_dtype), None


def inject_gradient(x: Tensor, g: Tensor) -> Tensor:
    """A scalar whose gradient with respect to ``x`` is ``g`` (same shape)."""
    if x.shape != g.shape:
        raise ValueError(f"gradient {tuple(g.shape)} does not match tensor {tuple(x.shape)}")
    return _InjectGradient.apply(x, g.detach().to(work_dtype(x)))


def _require_finite(name: str, x: Tensor) -> None:
    if not bool(torch.isfinite(x).all()):
        bad = int((~torch.isfinite(x)).sum())
        raise NonFiniteInputError(f"{name} holds {bad} NaN/Inf values of {x.numel()}; the 3D state is corrupt")


def _sanitize(g: Tensor, clip: float | None) -> Tensor:
    # Non-finite entries carry no direction: drop them rather than let one overflow poison a step.
    g = torch.nan_to_num(g, nan=0.0, posinf=0.0, neginf=0.0)
    return g.clamp(-clip, clip) if clip is not None else g


def _randn_like(z0: Tensor, generator: torch.Generator | None) -> Tensor:
    # Draw where the generator lives (a CPU generator keeps runs reproducible across devices).
    device = generator.device if generator is not None else z0.device
    return to_device(torch.randn(z0.shape, generator=generator, dtype=work_dtype(z0), device=device), z0.device)


def _draw(
    term: PriorTerm, z0: Tensor, schedule: NoiseSchedule, step: int, generator: torch.Generator | None
) -> TermDraw:
    b = z0.shape[0]
    t = sample_timesteps(term.t_range, step, b, schedule.num_timesteps, generator, z0.device)
    if term.mode != "vsd":
        return TermDraw(t, _randn_like(z0, generator))
    ft = sample_timesteps(term.finetune_t_range, step, b, schedule.num_timesteps, generator, z0.device)
    return TermDraw(t, _randn_like(z0, generator), ft, _randn_like(z0, generator))


def _draw_objects(
    term: PriorTerm, z0: Tensor, schedule: NoiseSchedule, step: int,
    generators: torch.Generator | Sequence[torch.Generator] | None,
) -> TermDraw:
    """One draw per object from that object's own generator, so an object optimised in a batch
    sees the very t and ε it would see alone (equal-sized, object-major rows)."""
    if generators is None or isinstance(generators, torch.Generator):
        return _draw(term, z0, schedule, step, generators)
    parts = [_draw(term, z, schedule, step, g) for z, g in zip(z0.chunk(len(generators)), generators, strict=True)]

    def cat(name: str) -> Tensor | None:
        values = [getattr(p, name) for p in parts]
        return None if values[0] is None else torch.cat(values)

    return TermDraw(cat("t"), cat("noise"), cat("finetune_t"), cat("finetune_noise"))  # type: ignore[arg-type]


def hybrid_guidance(
    config: GuidanceConfig,
    bindings: Mapping[str, PriorBinding],
    schedule: NoiseSchedule,
    novel: Tensor,
    step: int,
    reference_render: Tensor | None = None,
    reference: Tensor | None = None,
    generator: torch.Generator | Sequence[torch.Generator] | None = None,
    draws: Sequence[TermDraw] | None = None,
    objects: int = 1,
) -> GuidanceOutput:
    """One step of Algorithm 1 for renders ``novel`` (B×3×H×W) of randomly sampled cameras.

    ``reference_render`` is the render of the reference camera and ``reference`` the photo y
    (same shape); pass both or neither. ``draws`` fixes t and ε per term (one per term, in order).

    ``objects`` > 1: the rows are that many independent objects, object-major (``novel`` holds
    B/objects views of each, ``reference`` one row each). Expectations are then taken per object
    and summed over objects, so each object's gradient equals its gradient alone; ``generator``
    may then be one generator per object (see ``_draw_objects``).
    """
    if (reference_render is None) != (reference is None):
        raise ValueError("pass both reference_render and reference, or neither")
    if objects < 1 or novel.shape[0] % objects or (reference is not None and reference.shape[0] % objects):
        raise ValueError(f"{novel.shape[0]} renders (and the references) must split evenly into {objects} objects")
    if not isinstance(generator, torch.Generator | None) and len(generator) != objects:
        raise ValueError(f"{len(generator)} generators given for {objects} objects")
    missing = [n for n in config.prior_names if n not in bindings]
    if missing:
        raise KeyError(f"guidance config names priors {missing} but only {sorted(bindings)} are bound")
    for name in config.needs_finetuned:
        if bindings[name].finetuned is None:
            raise ValueError(f"prior {name!r} is used in VSD mode but has no fine-tuned counterpart bound")
    if draws is not None and len(draws) != len(config.terms):
        raise ValueError(f"{len(draws)} draws given for {len(config.terms)} prior terms")
    if config.check_inputs:
        _require_finite("novel-view render", novel)
        if reference is not None:
            _require_finite("reference-view render", reference_render)
            _require_finite("reference image", reference)

    stats: dict[str, Tensor] = {}
    loss = novel.new_zeros((), dtype=work_dtype(novel))
    finetune_loss = novel.new_zeros((), dtype=work_dtype(novel))
    encoded: dict[str, Tensor] = {}
    views = novel.shape[0] // objects  # the expectation over cameras is per object

    for i, term in enumerate(config.terms):
        if not term.is_active:
            continue
        bind = bindings[term.prior]
        if term.prior not in encoded:  # one encode per prior even when it has several terms
            encoded[term.prior] = bind.prior.encode(novel)
        z0 = encoded[term.prior]
        draw = draws[i] if draws is not None else _draw_objects(term, z0, schedule, step, generator)
        zt = schedule.add_noise(z0.detach(), draw.noise.to(z0), draw.t)
        with torch.no_grad():
            eps_pred = bind.prior.predict_noise(zt, draw.t, bind.condition, term.cfg_scale)
            if term.mode == "vsd":
                eps_phi = bind.finetuned.predict_noise(zt, draw.t, bind.condition, term.finetuned_cfg_scale)
            else:
                eps_phi = draw.noise
        wd = work_dtype(z0)
        residual = eps_pred.to(wd) - eps_phi.to(device=eps_pred.device, dtype=wd)
        # Counted before sanitising, so callers can treat a step with a broken prior as bad.
        stats[f"term{i}/{term.prior}/nonfinite"] = (~torch.isfinite(residual)).sum()
        residual = torch.nan_to_num(residual, nan=0.0, posinf=0.0, neginf=0.0)
        filtered = sum(f.k * filter_residual(residual, f.band) for f in term.filters)
        w = schedule.weight(draw.t, term.weighting, like=residual)
        g = _sanitize(config.lambda_c * w * filtered / views, config.grad_clip)
        loss = loss + inject_gradient(z0, g)
        stats[f"term{i}/{term.prior}/grad_norm"] = g.detach().norm()
        stats[f"term{i}/{term.prior}/t_mean"] = draw.t.float().mean()

        if term.mode == "vsd":
            ft = draw.finetune_t
            fnoise = draw.finetune_noise
            if ft is None or fnoise is None:
                raise ValueError(f"VSD term {i} needs finetune_t and finetune_noise in its draw")
            fnoise = fnoise.to(z0)
            zft = schedule.add_noise(z0.detach(), fnoise, ft)
            pred = bind.finetuned.predict_noise(zft, ft, bind.condition, 1.0)
            ft_loss = (pred.to(wd) - fnoise.to(wd)).pow(2).mean() * objects  # Σ over objects of their means
            finetune_loss = finetune_loss + ft_loss
            stats[f"term{i}/{term.prior}/finetune_loss"] = ft_loss.detach()

        if reference is not None:
            ref_scale = (1.0 - config.lambda_c) / config.sigma**2
            for m, f in enumerate(term.filters):
                if f.k == 0.0:
                    continue
                rl = reference_loss(reference_render, reference, f.band, objects)
                loss = loss + f.k * ref_scale * rl
                stats[f"term{i}/{term.prior}/ref{m}"] = rl.detach()

    return GuidanceOutput(loss=loss, finetune_loss=finetune_loss, stats=stats)
