"""The resumable, guarded optimisation loop every optimising stage runs.

A stage supplies a ``StageTask`` (its parameters, optimisers and one step's loss); this loop owns
everything that must be identical across stages: resume from the newest valid checkpoint,
checkpoints every N steps, the random state, numerical guards and the error-against-time log.

Resume is exact: a checkpoint holds the task state (parameters, optimiser moments, LoRA adapters,
occupancy grids…), both random generators, the step, the loss history and the guard counters,
so a run killed at any point and restarted replays the same updates (bit-identical on CPU).

Guards: a step whose loss, prior output or gradients hold NaN/Inf is skipped (no update), and one
that leaves non-finite parameters is rolled back at once. After ``max_bad_steps`` consecutive bad
steps the last good state (the newest checkpoint, or the start) is restored. Every event is
counted; ``NonFiniteStateError`` from the checkpoint writer guarantees no NaN is ever saved.

Early stopping: at each log row the task says whether its scene has converged
(``ops.engine.early_stop``); the loop then ends before ``steps`` and the result says where.
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Protocol

import torch
from torch import Tensor, nn

from assets_store.checkpoints import Checkpoints

_AUTOCAST: dict[str, torch.dtype | None] = {"float32": None, "bfloat16": torch.bfloat16, "float16": torch.float16}


class BadStep(RuntimeError):
    """A task's step could not produce a usable loss (e.g. the surface vanished): skip it."""


@dataclass(frozen=True)
class LoopConfig:
    """The schedule, checkpoints, guards and precision of one optimising stage's loop."""

    steps: int
    """Optimisation steps of the stage (the paper: NeRF 10k, DMTet 5k, texture 5k)."""
    checkpoint_every: int = 100
    """Steps between checkpoints: resume points, and the good state a run of bad steps is rolled back to."""
    log_every: int = 10
    """Steps between run-log rows (loss terms, evaluation metrics, progress); the last step is always logged."""
    grad_clip: float | None = 10.0
    """Largest global gradient norm per optimiser, clipped before each update; None: no clipping."""
    max_bad_steps: int = 3
    """Consecutive bad (non-finite, skipped) steps after which the last good state is restored."""
    keep_checkpoints: int = 2
    """How many of the newest checkpoints are kept on disk."""
    # Parameters, optimiser state and the evaluation stay float32 whatever the precision. Under
    # float16 the loss scale is dynamic: the small prior terms (λc = 5e-4) underflow without it, the
    # pixel-summed reference loss overflows with too much of it.
    precision: Literal["float32", "bfloat16", "float16"] = "float32"
    """Autocast dtype of each step's forward pass; float16 adds dynamic loss scaling (``fp16_*``)."""
    fp16_loss_scale: float = 1024.0
    """Initial float16 loss scale; it halves on a step whose gradients overflow (step skipped and counted)."""
    fp16_growth_interval: int = 100
    """Good float16 steps after which the loss scale doubles."""
    early_stop: bool = True
    """End the stage before ``steps`` once its reference-view PSNR stops improving (``early_stop_*``,
    ``ops.engine.early_stop``); false: the fixed schedule."""
    early_stop_patience: float = 0.1
    """Share of the schedule over which the best reference-view PSNR must improve for the stage to go on."""
    early_stop_min_share: float = 0.5
    """Share of the schedule every stage runs before it may stop."""
    early_stop_min_gain_db: float = 0.05
    """Gain (dB) of the best reference-view PSNR over the patience window that counts as still improving."""

    def __post_init__(self) -> None:
        if self.steps < 0:
            raise ValueError(f"steps must be ≥ 0, got {self.steps}")
        if self.checkpoint_every < 1 or self.log_every < 1 or self.max_bad_steps < 1:
            raise ValueError("checkpoint_every, log_every and max_bad_steps must be ≥ 1")
        if self.grad_clip is not None and not self.grad_clip > 0:
            raise ValueError(f"grad_clip must be > 0 when set, got {self.grad_clip}")
        if self.precision not in _AUTOCAST:
            raise ValueError(f"precision must be one of {sorted(_AUTOCAST)}, got {self.precision!r}")
        if not (math.isfinite(self.fp16_loss_scale) and self.fp16_loss_scale > 0):
            raise ValueError(f"fp16_loss_scale must be finite and > 0, got {self.fp16_loss_scale}")
        if self.fp16_growth_interval < 1:
            raise ValueError(f"fp16_growth_interval must be ≥ 1, got {self.fp16_growth_interval}")
        if not (0 < self.early_stop_patience <= 1 and 0 <= self.early_stop_min_share <= 1):
            raise ValueError(f"early_stop_patience must be in (0, 1] and early_stop_min_share in [0, 1], got "
                             f"{self.early_stop_patience} and {self.early_stop_min_share}")
        if not (math.isfinite(self.early_stop_min_gain_db) and self.early_stop_min_gain_db >= 0):
            raise ValueError(f"early_stop_min_gain_db must be finite and ≥ 0, got {self.early_stop_min_gain_db}")


@dataclass
class StepOutput:
    """``loss`` drives every optimiser of the task; ``terms`` are detached scalars for the log;
    ``nonfinite_prior`` counts NaN/Inf values the priors returned this step."""

    loss: Tensor
    terms: dict[str, Tensor] = field(default_factory=dict)
    nonfinite_prior: Tensor | int = 0


class StageTask(Protocol):
    def optimizers(self) -> Mapping[str, torch.optim.Optimizer]: ...

    def step(self, step: int, generator: torch.Generator) -> StepOutput: ...

    def after_step(self, ok: bool) -> None:
        """Updates outside the main optimisers (e.g. the VSD LoRA) after a good step; after a bad
        one, drop whatever gradients they received."""

    def state(self) -> dict[str, Any]: ...

    def load_state(self, state: Mapping[str, Any]) -> None: ...

    def evaluate(self) -> dict[str, float]:
        """Deterministic measurements for the log (must not draw from any generator)."""

    def stop_early(self, history: list[dict[str, Any]], done: int, config: LoopConfig) -> bool:
        """Whether the loop may end after step ``done`` (``ops.engine.early_stop``); asked at log rows only."""


@dataclass(frozen=True)
class ProgressEvent:
    stage: str
    step: int
    total: int
    elapsed_s: float
    metrics: dict[str, float]


ProgressFn = Callable[[ProgressEvent], None]


@dataclass
class GuardCounters:
    nonfinite_loss: int = 0
    nonfinite_prior: int = 0
    nonfinite_grad: int = 0
    nonfinite_param: int = 0
    bad_step: int = 0
    restores: int = 0

    @property
    def skipped(self) -> int:
        return self.nonfinite_loss + self.nonfinite_prior + self.nonfinite_grad + self.nonfinite_param + self.bad_step

    def as_dict(self) -> dict[str, int]:
        return {**{k: int(v) for k, v in vars(self).items()}, "skipped_steps": self.skipped}


@dataclass
class LoopResult:
    history: list[dict[str, Any]]
    guards: GuardCounters
    resumed_from: int | None
    steps_run: int
    wall_s: float
    schedule_steps: int = 0
    stopped_at: int | None = None
    """The step the loop ended at because the scene had converged; None: it ran its whole schedule."""


def _parameters(task: StageTask) -> Iterator[nn.Parameter]:
    for opt in task.optimizers().values():
        for group in opt.param_groups:
            yield from group["params"]


def _all_finite(tensors: list[Tensor]) -> bool:
    if not tensors:
        return True
    return bool(torch.isfinite(torch.stack([t.detach().abs().amax().float() for t in tensors])).all())


def _clone(state: Any) -> Any:
    """A deep copy that owns its tensors (state dicts alias live parameters)."""
    return copy.deepcopy(state)


@dataclass
class _LossScale:
    """The float16 loss scale (see ``LoopConfig.precision``); 1 and inert for other precisions."""

    value: float
    enabled: bool
    growth_interval: int
    good: int = 0

    def update(self, overflowed: bool) -> None:
        if not self.enabled:
            return
        if overflowed:
            self.value, self.good = max(self.value / 2.0, 2.0**-24), 0
            return
        self.good += 1
        if self.good >= self.growth_interval:
            self.value, self.good = min(self.value * 2.0, 2.0**24), 0


def _zero_grad(task: StageTask) -> None:
    for opt in task.optimizers().values():
        opt.zero_grad(set_to_none=True)


def _finite_or_none(x: float) -> float | None:
    return x if math.isfinite(x) else None


def run_loop(task: StageTask, config: LoopConfig, generator: torch.Generator, stage: str,
             checkpoint_dir: Path | None = None, progress: ProgressFn | None = None) -> LoopResult:
    """Run ``config.steps`` steps of ``task``, resuming from ``checkpoint_dir`` when it holds one."""
    # Gradients of the small prior terms decay into float32's subnormal range, where x86 CPUs run
    # 10–20× slower (measured: 0.22 → 4 s per draft NeRF step); flushing them to zero changes no
    # result that matters (they are below 1.2e-38).
    torch.set_flush_denormal(True)
    ckpts = Checkpoints(checkpoint_dir, keep=config.keep_checkpoints) if checkpoint_dir is not None else None
    history: list[dict[str, Any]] = []
    guards = GuardCounters()
    start, resumed_from, wall_before = 0, None, 0.0
    loaded = ckpts.load_latest() if ckpts is not None else None
    if loaded is not None:
        start, state = loaded
        task.load_state(state["task"])
        generator.set_state(state["rng"]["generator"])
        torch.set_rng_state(state["rng"]["torch"])
        history = list(state["history"])
        guards = GuardCounters(**state["guards"])
        wall_before = float(state["wall_s"])
        resumed_from = start
    half = config.precision == "float16"
    scale = _LossScale(config.fp16_loss_scale if half else 1.0, half, config.fp16_growth_interval)
    if loaded is not None and "loss_scale" in state:
        scale.value, scale.good = float(state["loss_scale"][0]), int(state["loss_scale"][1])
    good = _clone(task.state())
    t0 = time.perf_counter()
    consecutive = 0
    stopped_at: int | None = None

    def elapsed() -> float:
        return wall_before + time.perf_counter() - t0

    for step in range(start, config.steps):
        _zero_grad(task)
        ok, terms = _guarded_step(task, step, generator, config, guards, scale)
        task.after_step(ok)
        if ok:
            consecutive = 0
        else:
            consecutive += 1
            if consecutive >= config.max_bad_steps:
                task.load_state(_clone(good))
                guards.restores += 1
                consecutive = 0
        done = step + 1
        if step % config.log_every == 0 or done == config.steps:
            row: dict[str, Any] = {"step": done, "wall_s": round(elapsed(), 4), "ok": ok}
            row.update({k: _finite_or_none(float(v)) for k, v in terms.items()})
            row.update({k: _finite_or_none(v) for k, v in task.evaluate().items()})
            history.append(row)
            if progress is not None:
                progress(ProgressEvent(stage, done, config.steps, elapsed(), {
                    k: v for k, v in row.items() if isinstance(v, float) and k != "wall_s"}))
            if config.early_stop and done < config.steps and task.stop_early(history, done, config):
                stopped_at = done
                break
        if ckpts is not None and done % config.checkpoint_every == 0 and done < config.steps:
            state = task.state()
            ckpts.save(done, {
                "task": state,
                "rng": {"generator": generator.get_state(), "torch": torch.get_rng_state()},
                "history": history, "guards": vars(guards).copy(), "wall_s": elapsed(),
                "loss_scale": [scale.value, scale.good],
            })
            good = _clone(state)
    end = config.steps if stopped_at is None else stopped_at
    return LoopResult(history, guards, resumed_from, max(0, end - start), elapsed(), config.steps, stopped_at)


def _guarded_step(task: StageTask, step: int, generator: torch.Generator, config: LoopConfig,
                  guards: GuardCounters, scale: _LossScale) -> tuple[bool, dict[str, Tensor]]:
    dtype = _AUTOCAST[config.precision]
    device_type = next(_parameters(task)).device.type
    try:
        with torch.autocast(device_type, dtype=dtype or torch.float32, enabled=dtype is not None):
            out = task.step(step, generator)
    except BadStep:
        guards.bad_step += 1
        return False, {}
    terms = {"loss": out.loss.detach(), **out.terms}
    if int(out.nonfinite_prior) > 0:
        guards.nonfinite_prior += 1
        return False, terms
    if not bool(torch.isfinite(out.loss)):
        guards.nonfinite_loss += 1
        return False, terms
    (out.loss * scale.value).backward()
    params = [p for p in _parameters(task) if p.grad is not None]
    overflowed = not _all_finite([p.grad for p in params])
    scale.update(overflowed)
    if overflowed:
        guards.nonfinite_grad += 1
        _zero_grad(task)
        return False, terms
    if scale.value != 1.0:
        for p in params:
            p.grad.div_(scale.value)
        # Adapters outside the task's optimisers (VSD LoRAs) keep scaled gradients: Adam's update
        # does not depend on a constant scale, and this one changes by ×2 at most every 100 steps.
    before = [p.detach().clone() for p in params]
    for opt in task.optimizers().values():
        if config.grad_clip is not None:
            group_params = [p for g in opt.param_groups for p in g["params"] if p.grad is not None]
            torch.nn.utils.clip_grad_norm_(group_params, config.grad_clip)
        opt.step()
    if not _all_finite(params):
        guards.nonfinite_param += 1
        with torch.no_grad():  # roll this step back at once; the optimiser moments are already
            for p, b in zip(params, before, strict=True):  # finite (checked gradients)
                p.copy_(b)
        return False, terms
    return True, terms
