"""The resumable, guarded optimisation loop every optimising stage runs.

A stage supplies a ``StageTask`` (its parameters, optimisers and one step's loss); this loop owns
everything that must be identical across stages: resume from the newest valid checkpoint,
checkpoints every N steps, the random state, numerical guards and the error-against-time log.

Resume is exact: a checkpoint holds the task state (parameters, optimiser moments, LoRA adapters,
occupancy grids…), both random generators, the step, the loss history and the guard counters,
so a run killed at any point and restarted replays the same updates (bit-identical on CPU).

Guards: a step whose loss, prior output or gradients hold NaN/Inf is skipped (no update). The
decision is made on the device: fused optimisers skip on a device flag
(``morpheus_core.runtime.device_skip``), so a step needs no host sync; the counts are read at log
and checkpoint rows. There, parameters a step left non-finite, or a run of ``max_bad_steps`` bad
steps still going, restore the last good state (the newest checkpoint, or the start); skipped steps
change nothing, so finding them a few steps late loses nothing. Every event is counted;
``NonFiniteStateError`` from the checkpoint writer guarantees no NaN is ever saved.

Early stopping: at each log row the task says whether its scene has converged
(``ops.engine.early_stop``); the loop then ends before ``steps`` and the result says where.
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Protocol

import torch
from torch import Tensor, nn

from assets_store.checkpoints import Checkpoints
from morpheus_core.runtime.device_skip import nonfinite, step_or_skip
from ops.engine.progress import Heartbeat, ProgressEvent, ProgressFn

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
    early_stop: bool = False
    """End the stage before ``steps`` once its reference-view PSNR stops improving (``early_stop_*``,
    ``ops.engine.early_stop``); false (the default): the fixed schedule. Off by default because the
    reference view converges before the sides the photo does not show: at the paper schedule's tenth
    (H200, oracle priors) stopping the NeRF and DMTet stages saved 26 % / 28 % of their steps and cost
    0.5 ± 1.1 dB GLB novel-view PSNR, up to 1.8 dB on one scene; in the texture stage 0.1–0.2 dB on
    every scene (``benchmarks/results/early_stop_paper10_h200.md``, ``early_stop_texture_h200.md``). Those runs
    stopped on the reference view alone; the side-view watch below (``early_stop_watch_sides``) is meant to fix
    that and is not yet measured on a GPU."""
    early_stop_patience: float = 0.1
    """Share of the schedule over which the best reference-view PSNR must improve for the stage to go on."""
    early_stop_min_share: float = 0.5
    """Share of the schedule every stage runs before it may stop."""
    early_stop_min_gain_db: float = 0.05
    """Gain (dB) of the best reference-view PSNR over the patience window that counts as still improving."""
    early_stop_watch_sides: bool = True
    """With ``early_stop``: stop only once held-out views of the sides and back also move no more coherently
    than a random walk over the patience window (``sides_drift`` ≤ 1, ``ops.engine.early_stop.SideWatch``);
    false: the reference view decides alone."""

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

    def after_step(self, ok: Tensor | bool) -> None:
        """Updates outside the main optimisers (e.g. the VSD LoRA) after a good step; after a bad
        one, drop whatever gradients they received. ``ok`` is a bool on the device when the step ran
        (``morpheus_core.runtime.device_skip`` applies it without a host sync), False when it raised ``BadStep``."""

    def state(self) -> dict[str, Any]: ...

    def load_state(self, state: Mapping[str, Any]) -> None: ...

    def evaluate(self, done: int) -> dict[str, float]:
        """Deterministic measurements for the log row after step ``done`` (must not draw from any generator)."""

    def stop_early(self, history: list[dict[str, Any]], done: int, config: LoopConfig) -> bool:
        """Whether the loop may end after step ``done`` (``ops.engine.early_stop``); asked at log rows only."""


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


class _LossScale:
    """The float16 loss scale (see ``LoopConfig.precision``), on the device; 1 and inert otherwise."""

    def __init__(self, value: float, good: int, enabled: bool, growth_interval: int, device: torch.device) -> None:
        self.value = torch.tensor(value, dtype=torch.float32, device=device)
        self.good = torch.tensor(good, dtype=torch.int64, device=device)
        self.enabled, self.growth_interval = enabled, growth_interval

    def update(self, overflowed: Tensor, counted: Tensor) -> None:
        """Halve on an overflow, double after ``growth_interval`` good steps; steps not ``counted``
        (skipped before their gradients were checked) leave it as it is."""
        if not self.enabled:
            return
        good = torch.where(overflowed, 0, self.good + 1)
        grow = good >= self.growth_interval
        value = torch.where(overflowed, (self.value / 2).clamp_min(2.0**-24),
                            torch.where(grow, (self.value * 2).clamp_max(2.0**24), self.value))
        self.value = torch.where(counted, value, self.value)
        self.good = torch.where(counted, torch.where(grow, 0, good), self.good)


class _Guards:
    """The guards' per-step findings, counted on the device so that a step needs no host sync; the
    loop reads them (``read``) at log and checkpoint rows only."""

    def __init__(self, counters: GuardCounters, device: torch.device) -> None:
        self.counters = counters
        self.device = device
        self.pending = torch.zeros(3, dtype=torch.int64, device=device)  # prior, loss, grad
        self.run = torch.zeros((), dtype=torch.int64, device=device)  # bad steps in a row, now

    def record(self, prior: Tensor, loss: Tensor, grad: Tensor) -> Tensor:
        """Count one step's (exclusive) causes; returns whether the step was bad."""
        causes = torch.stack((prior, loss, grad))
        bad = causes.any()
        self.pending += causes.long()
        self.run = (self.run + 1) * bad
        return bad

    def record_bad_step(self) -> None:
        self.counters.bad_step += 1
        self.run = self.run + 1

    def read(self) -> int:
        """Fold the pending counts into ``counters``; returns the current run of bad steps."""
        prior, loss, grad, run = torch.cat((self.pending, self.run.reshape(1))).tolist()
        self.counters.nonfinite_prior += prior
        self.counters.nonfinite_loss += loss
        self.counters.nonfinite_grad += grad
        self.pending.zero_()
        return int(run)

    def reset_run(self) -> None:
        self.run = torch.zeros_like(self.run)


def _zero_grad(task: StageTask) -> None:
    for opt in task.optimizers().values():
        opt.zero_grad(set_to_none=True)


def _finite_or_none(x: float) -> float | None:
    return x if math.isfinite(x) else None


def run_loop(task: StageTask, config: LoopConfig, generator: torch.Generator, stage: str,
             checkpoint_dir: Path | None = None, progress: ProgressFn | None = None,
             heartbeat_s: float | None = None) -> LoopResult:
    """Run ``config.steps`` steps of ``task``, resuming from ``checkpoint_dir`` when it holds one.

    ``progress`` hears of every log row and, between them, every ``heartbeat_s`` seconds (None:
    ``HEARTBEAT_S``) of the step reached (``ops.engine.progress.Heartbeat``): slow steps or a large ``log_every`` never
    leave the console silent."""
    # Gradients of the small prior terms decay into float32's subnormal range, where x86 CPUs run
    # 10–20× slower (measured: 0.22 → 4 s per draft NeRF step); flushing them to zero changes no
    # result that matters (they are below 1.2e-38).
    torch.set_flush_denormal(True)
    ckpts = Checkpoints(checkpoint_dir, keep=config.keep_checkpoints) if checkpoint_dir is not None else None
    history: list[dict[str, Any]] = []
    counters = GuardCounters()
    start, resumed_from, wall_before = 0, None, 0.0
    loaded = ckpts.load_latest() if ckpts is not None else None
    if loaded is not None:
        start, state = loaded
        task.load_state(state["task"])
        generator.set_state(state["rng"]["generator"])
        torch.set_rng_state(state["rng"]["torch"])
        history = list(state["history"])
        counters = GuardCounters(**state["guards"])
        wall_before = float(state["wall_s"])
        resumed_from = start
    device = next(_parameters(task)).device
    guards = _Guards(counters, device)
    half = config.precision == "float16"
    value, good_steps = config.fp16_loss_scale if half else 1.0, 0
    if loaded is not None and "loss_scale" in state:
        value, good_steps = float(state["loss_scale"][0]), int(state["loss_scale"][1])
    scale = _LossScale(value, good_steps, half, config.fp16_growth_interval, device)
    good = _clone(task.state())
    beat = Heartbeat(progress, stage, config.steps, every_s=heartbeat_s, elapsed_before=wall_before)
    beat.step = start
    t0 = time.perf_counter()
    stopped_at: int | None = None

    def elapsed() -> float:
        return wall_before + time.perf_counter() - t0

    def check() -> None:
        # A run of bad steps that is still going, or parameters a step left non-finite: back to the
        # last good state. Bad steps changed nothing, so finding them a few steps late loses nothing.
        run = guards.read()
        if not _all_finite(list(_parameters(task))):
            counters.nonfinite_param += 1
        elif run < config.max_bad_steps:
            return
        else:
            counters.restores += 1
        task.load_state(_clone(good))
        guards.reset_run()

    with beat:
        for step in range(start, config.steps):
            _zero_grad(task)
            ok, terms = _guarded_step(task, step, generator, config, guards, scale)
            task.after_step(ok)
            done = step + 1
            beat.step = done
            log_row = step % config.log_every == 0 or done == config.steps
            save = ckpts is not None and done % config.checkpoint_every == 0 and done < config.steps
            if log_row or save:
                check()
            if log_row:
                row: dict[str, Any] = {"step": done, "wall_s": round(elapsed(), 4), "ok": bool(ok)}
                row.update({k: _finite_or_none(float(v)) for k, v in terms.items()})
                row.update({k: _finite_or_none(v) for k, v in task.evaluate(done).items()})
                history.append(row)
                if progress is not None:
                    beat(ProgressEvent(stage, done, config.steps, elapsed(), {
                        k: v for k, v in row.items() if isinstance(v, float) and k != "wall_s"}))
                if config.early_stop and done < config.steps and task.stop_early(history, done, config):
                    stopped_at = done
                    break
            if save:
                state = task.state()
                ckpts.save(done, {  # type: ignore[union-attr]
                    "task": state,
                    "rng": {"generator": generator.get_state(), "torch": torch.get_rng_state()},
                    "history": history, "guards": vars(counters).copy(), "wall_s": elapsed(),
                    "loss_scale": [float(scale.value), int(scale.good)],
                })
                good = _clone(state)
    end = config.steps if stopped_at is None else stopped_at
    return LoopResult(history, counters, resumed_from, max(0, end - start), elapsed(), config.steps, stopped_at)


def _flag(count: Tensor | int, device: torch.device) -> Tensor:
    """``count > 0`` as a bool on ``device``; a host int becomes a filled tensor, not a (syncing) copy."""
    if isinstance(count, Tensor):
        return count.to(device) > 0
    return torch.full((), count > 0, dtype=torch.bool, device=device)


def _guarded_step(task: StageTask, step: int, generator: torch.Generator, config: LoopConfig,
                  guards: _Guards, scale: _LossScale) -> tuple[Tensor | bool, dict[str, Tensor]]:
    """One step, its guards decided on the device: a bad step's update is skipped by the optimiser."""
    dtype = _AUTOCAST[config.precision]
    try:
        with torch.autocast(guards.device.type, dtype=dtype or torch.float32, enabled=dtype is not None):
            out = task.step(step, generator)
    except BadStep:
        guards.record_bad_step()
        return False, {}
    loss = out.loss
    terms = {"loss": loss.detach(), **out.terms}
    prior_bad = _flag(out.nonfinite_prior, guards.device)
    loss_bad = ~torch.isfinite(loss.detach()) & ~prior_bad
    early = prior_bad | loss_bad
    if loss.requires_grad:  # a bad loss still back-propagates: its update is skipped below
        (loss * scale.value if scale.enabled else loss).backward()
    params = [p for p in _parameters(task) if p.grad is not None]
    grad_bad = nonfinite([p.grad for p in params], guards.device, scale.value.reciprocal()) & ~early  # type: ignore[misc]
    scale.update(grad_bad, ~early)
    # Adapters outside the task's optimisers (VSD LoRAs) keep scaled gradients: Adam's update does
    # not depend on a constant scale, and this one changes by ×2 at most every 100 steps.
    bad = guards.record(prior_bad, loss_bad, grad_bad)
    for opt in task.optimizers().values():
        if config.grad_clip is not None:
            group_params = [p for g in opt.param_groups for p in g["params"] if p.grad is not None]
            torch.nn.utils.clip_grad_norm_(group_params, config.grad_clip)
        step_or_skip(opt, bad)
    return ~bad, terms
