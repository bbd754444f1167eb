"""Discrete diffusion schedule shared by every prior: ᾱ_t, the weighting w(t), timestep sampling.

Timesteps are integers in [0, T) as in diffusers; ``t_range`` fractions map to
[int(lo·T), int(hi·T)] inclusive. The upper bound can be annealed by optimisation step (the paper
anneals [0.02, 0.98] to [0.02, 0.50] at step 5k of the NeRF stage).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from morpheus_core.runtime.devices import to_device

Weighting = Literal["one_minus_alpha_bar", "uniform"]


def work_dtype(x: Tensor) -> torch.dtype:
    """Precision for guidance arithmetic: float64 stays exact, everything else runs in float32."""
    return torch.float64 if x.dtype == torch.float64 else torch.float32


@dataclass(frozen=True)
class NoiseScheduleConfig:
    """Scaled-linear betas (Stable Diffusion, Zero123): sqrt-linear from beta_start to beta_end."""

    num_train_timesteps: int = 1000
    beta_start: float = 0.00085
    beta_end: float = 0.012


class NoiseSchedule:
    """ᾱ_t table plus the forward process x_t = √ᾱ_t x0 + √(1 − ᾱ_t) ε."""

    def __init__(self, config: NoiseScheduleConfig | None = None) -> None:
        self.config = config or NoiseScheduleConfig()
        c = self.config
        if c.num_train_timesteps < 2 or not 0.0 < c.beta_start <= c.beta_end < 1.0:
            raise ValueError(f"invalid noise schedule {c}")
        betas = torch.linspace(
            math.sqrt(c.beta_start), math.sqrt(c.beta_end), c.num_train_timesteps, dtype=torch.float64
        ).pow(2)
        self.alphas_cumprod = torch.cumprod(1.0 - betas, dim=0)
        self._on_device: dict[torch.device, Tensor] = {}  # the table copied once per device, not per call

    @property
    def num_timesteps(self) -> int:
        return self.config.num_train_timesteps

    def _check(self, t: Tensor) -> Tensor:
        if t.dtype.is_floating_point or t.dtype == torch.bool:
            raise TypeError(f"timesteps must be integers, got {t.dtype}")
        if t.device.type != "cpu":  # asserted on the device: reading the values back would sync every call
            torch._assert_async(((t >= 0) & (t < self.num_timesteps)).all(),
                                f"timesteps must lie in [0, {self.num_timesteps})")
        elif t.numel() and (int(t.min()) < 0 or int(t.max()) >= self.num_timesteps):
            raise ValueError(f"timesteps must lie in [0, {self.num_timesteps}), got {t.tolist()}")
        return t

    def _table(self, device: torch.device) -> Tensor:
        if device not in self._on_device:
            self._on_device[device] = self.alphas_cumprod.to(device)
        return self._on_device[device]

    def alpha_bar(self, t: Tensor, like: Tensor | None = None) -> Tensor:
        """ᾱ_t in float32 (float64 when ``like`` is float64), shaped to broadcast against ``like``."""
        dtype = work_dtype(like) if like is not None else torch.float32
        ab = self._table(t.device)[self._check(t).long()].to(dtype)
        if like is not None:
            ab = ab.reshape(-1, *([1] * (like.dim() - 1)))
        return ab

    def add_noise(self, x0: Tensor, noise: Tensor, t: Tensor) -> Tensor:
        ab = self.alpha_bar(t, like=x0)
        wd = ab.dtype
        return (ab.sqrt() * x0.to(wd) + (1.0 - ab).sqrt() * noise.to(wd)).to(x0.dtype)

    def weight(self, t: Tensor, kind: Weighting, like: Tensor | None = None) -> Tensor:
        """w(t): 1 − ᾱ_t (the paper's choice) or uniform."""
        ab = self.alpha_bar(t, like=like)
        if kind == "one_minus_alpha_bar":
            return 1.0 - ab
        if kind == "uniform":
            return torch.ones_like(ab)
        raise ValueError(f"unknown weighting {kind!r}")


def apply_cfg(eps_uncond: Tensor, eps_cond: Tensor, scale: float) -> Tensor:
    """Classifier-free guidance ε_u + s(ε_c − ε_u); s = 1 is the conditional prediction."""
    return eps_uncond + scale * (eps_cond - eps_uncond)


@dataclass(frozen=True)
class TimestepRange:
    """t ∈ [lo, hi]·T whose upper bound moves linearly from ``hi`` to ``hi_end`` between steps
    ``anneal_start`` and ``anneal_end`` (a step change when they are one apart)."""

    lo: float = 0.02
    hi: float = 0.98
    hi_end: float | None = None
    anneal_start: int = 0
    anneal_end: int = 0

    def __post_init__(self) -> None:
        for name in ("lo", "hi") + (("hi_end",) if self.hi_end is not None else ()):
            v = getattr(self, name)
            if not (math.isfinite(v) and 0.0 <= v <= 1.0):
                raise ValueError(f"timestep fraction {name}={v} must lie in [0, 1]")
        if self.lo > min(self.hi, self.hi if self.hi_end is None else self.hi_end):
            raise ValueError(f"timestep range lower bound {self.lo} exceeds its upper bound")
        if self.anneal_end < self.anneal_start:
            raise ValueError("anneal_end must not precede anneal_start")

    def bounds(self, step: int) -> tuple[float, float]:
        if self.hi_end is None or step <= self.anneal_start:
            return self.lo, self.hi
        if step >= self.anneal_end:
            return self.lo, self.hi_end
        frac = (step - self.anneal_start) / (self.anneal_end - self.anneal_start)
        return self.lo, self.hi + frac * (self.hi_end - self.hi)

    def integer_bounds(self, step: int, num_timesteps: int) -> tuple[int, int]:
        lo, hi = self.bounds(step)
        t_lo = min(int(lo * num_timesteps), num_timesteps - 1)
        t_hi = min(int(hi * num_timesteps), num_timesteps - 1)
        return t_lo, max(t_lo, t_hi)


def sample_timesteps(
    t_range: TimestepRange,
    step: int,
    batch: int,
    num_timesteps: int,
    generator: torch.Generator | None = None,
    device: torch.device | str = "cpu",
) -> Tensor:
    """Uniform integer timesteps in the (annealed) range for this optimisation step."""
    t_lo, t_hi = t_range.integer_bounds(step, num_timesteps)
    gen_device = generator.device if generator is not None else "cpu"
    t = torch.randint(t_lo, t_hi + 1, (batch,), generator=generator, device=gen_device)
    return to_device(t, device)
