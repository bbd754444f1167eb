"""The optimising loop's learning-rate schedule (``LoopConfig.lr_final``, ``lr_decay_start``): constant, then a
half cosine down to a share of each configured rate.

Why decay at all: a diffusion prior's gradient is a different guess at every noise draw, so at a
constant rate the parameters keep wandering around what the priors agree on, by an amount the rate
sets (a noise floor); a falling rate averages the late guesses instead. The paper's rates are
constant, and so is the default."""

from __future__ import annotations

import math
from collections.abc import Iterable

import torch


def lr_multiplier(step: int, steps: int, final: float, decay_start: float) -> float:
    """The rates' multiplier at ``step`` (0-based) of ``steps``: 1 until ``decay_start`` × ``steps``, then a
    half cosine down to ``final`` at the last step. A function of the step alone, so a resumed run decays
    exactly as an uninterrupted one."""
    start = decay_start * steps
    last = steps - 1
    if final == 1 or step <= start or last <= start:
        return 1.0
    t = min(1.0, (step - start) / (last - start))
    return final + (1 - final) * 0.5 * (1 + math.cos(math.pi * t))


def set_learning_rates(optimizers: Iterable[torch.optim.Optimizer], multiplier: float) -> None:
    """Each parameter group's rate: its configured rate × ``multiplier``. The configured rate is kept in the
    group as ``base_lr``, so it travels with the optimiser's state into checkpoints and back."""
    for opt in optimizers:
        for group in opt.param_groups:
            group["lr"] = group.setdefault("base_lr", group["lr"]) * multiplier
