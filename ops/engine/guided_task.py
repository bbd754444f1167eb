"""What the three optimising stages' tasks share: their state, the prior suite's updates, evaluation.

A subclass names its modules and optimiser groups and implements ``render_step`` (this step's
renders and its own losses) and ``render_eval``; the guidance call, the checkpointed state (every
module's state dict, the Adam moments, the priors' LoRA state), the VSD counterpart updates and
the reference-view PSNR for the run log are the same for all of them. Splitting the renders from
the guidance is what lets ``ops.engine.batch`` guide many objects with one prior forward.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import torch
from torch import Tensor, nn

from morpheus_core.cameras import Cameras
from morpheus_core.guidance.diffusion import NoiseSchedule
from morpheus_core.guidance.hybrid import GuidanceOutput, hybrid_guidance
from morpheus_core.guidance.loss_balance import scaled_total
from morpheus_core.guidance.presets import GuidanceSettings
from morpheus_core.render.output import RenderOutput
from ops.engine.early_stop import METRIC, SIDE_VIEW_SIZE, SIDES_METRIC, SideWatch, converged, window_steps
from ops.engine.loop import LoopConfig, StepOutput
from ops.engine.priors import PriorSuite
from ops.engine.render_phases import RenderSchedule, StepShape
from ops.engine.target import ReferenceTarget, reference_psnr


def adam(groups: list[dict[str, Any]]) -> torch.optim.Adam:
    """The paper's Adam (0.9, 0.99); eps 1e-15 as in instant-ngp, so tiny hash-grid gradients move.
    Fused: one kernel for all parameters, and it skips a bad step on a device flag (``ops.engine.loop``)."""
    return torch.optim.Adam(groups, betas=(0.9, 0.99), eps=1e-15, fused=True)


@dataclass
class RenderedStep:
    """One object's renders for a step: the random views (V×3×H×W) and their cameras, the
    reference-view render (1×3×H×W), and the stage's own loss terms (mask, regularisers)."""

    cameras: Cameras
    novel: Tensor
    reference: Tensor
    extra_loss: Tensor
    terms: dict[str, Tensor] = field(default_factory=dict)


def step_output(out: GuidanceOutput, extra_loss: Tensor, terms: dict[str, Tensor], vsd: bool) -> StepOutput:
    """A step's loss: the guidance (θ), the VSD counterparts' loss (φ) and the stage's own terms, balanced
    as the official code balances them (``morpheus_core.guidance.loss_balance``)."""
    terms = {"guidance": out.loss.detach(), **({"finetune": out.finetune_loss.detach()} if vsd else {}), **terms}
    return StepOutput(scaled_total(out.loss, extra_loss, out.finetune_loss), terms, out.nonfinite_prior_values)


class GuidedTask(ABC):
    """A ``StageTask`` over ``modules`` trained by one Adam over ``groups`` under ``guidance``, its steps
    rendered as ``renders`` says (``target`` is the photo at the final render size)."""

    def __init__(self, target: ReferenceTarget, suite: PriorSuite, guidance: GuidanceSettings,
                 renders: RenderSchedule, modules: dict[str, nn.Module], groups: list[dict[str, Any]],
                 device: torch.device, loop: LoopConfig) -> None:
        self.target, self.suite, self.device = target, suite, device
        self.renders = renders
        # The held-out views cost three small renders a log row: only where they can stop the stage.
        watched = loop.early_stop and loop.early_stop_watch_sides
        self.sides = SideWatch(window_steps(loop), target.camera) if watched else None
        self._targets = {target.resolution: target}
        self.modules = modules
        # The loop's device-side guards skip a step with a non-finite render (its prior outputs or its
        # loss are then non-finite); the guidance's own check would stop the host three times a step.
        self.guidance = replace(guidance.build(renders.steps), check_inputs=False)
        self.schedule = NoiseSchedule()
        self.opt = adam(groups)
        self.shared_by = 1
        """How many objects share this task's steps (``ops.engine.batch.BatchTask`` sets it)."""

    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        return {"adam": self.opt}

    def shape(self, step: int) -> StepShape:
        """What step ``step`` renders (its render phase)."""
        return self.renders.at(step)

    def target_at(self, resolution: int) -> ReferenceTarget:
        """The photo at a render size of this stage's phases (made once per size)."""
        if resolution not in self._targets:
            self._targets[resolution] = self.target.resized(resolution)
        return self._targets[resolution]

    @abstractmethod
    def render_step(self, step: int, generator: torch.Generator) -> RenderedStep:
        """This step's renders (reference view and random views, at ``shape(step)``) and the stage's
        own losses."""

    def step(self, step: int, generator: torch.Generator) -> StepOutput:
        """One step's loss: the reference view and random views under the guidance."""
        r = self.render_step(step, generator)
        out = hybrid_guidance(self.guidance, self.suite.bindings(r.cameras, r.novel), self.schedule, r.novel, step,
                              r.reference, self.target_at(r.reference.shape[-1]).rgb, generator)
        return step_output(out, r.extra_loss, r.terms, bool(self.guidance.needs_finetuned))

    @abstractmethod
    def render_eval(self, cameras: Any, size: int | None = None) -> RenderOutput:
        """A deterministic render (no generator) for previews and the run log."""

    def after_step(self, ok: Tensor | bool) -> None:
        self.suite.after_step(ok)

    def state(self) -> dict[str, Any]:
        return {**{name: m.state_dict() for name, m in self.modules.items()},
                "opt": self.opt.state_dict(), "priors": self.suite.state(),
                **({"sides": self.sides.state()} if self.sides is not None else {})}

    def load_state(self, state: Mapping[str, Any]) -> None:
        for name, m in self.modules.items():
            m.load_state_dict(state[name])
        self.opt.load_state_dict(state["opt"])
        self.suite.load_state(state["priors"])
        if self.sides is not None and "sides" in state:
            self.sides.load_state(state["sides"])

    @torch.no_grad()
    def ref_psnr(self) -> float:
        """PSNR (dB) of the deterministic reference-view render against the photo."""
        return reference_psnr(self.render_eval(self.target.camera).rgb_chw(), self.target)

    def evaluate(self, done: int) -> dict[str, float]:
        """The log row's measurements: the reference-view PSNR and, when the sides are watched, their change."""
        out = {METRIC: self.ref_psnr()}
        if self.sides is not None:
            with torch.no_grad():
                out.update(self.sides.observe(done, self.render_eval(self.sides.cameras, SIDE_VIEW_SIZE).rgb_chw()))
        return out

    def last_phase(self, step: int) -> bool:
        """Whether the stage's own schedule has reached its last phase by ``step``: a stage never
        stops inside a coarse render phase (the NeRF stage adds its hash-grid levels)."""
        return step >= self.renders.final_from()

    def stop_early(self, history: list[dict[str, Any]], done: int, config: LoopConfig, prefix: str = "") -> bool:
        """``ops.engine.early_stop.converged`` on this task's columns (``prefix``: its batch index's), once in the
        last phase."""
        sides = prefix + SIDES_METRIC if self.sides is not None else None
        return self.last_phase(done) and converged(history, done, config, prefix + METRIC, sides)
