"""One object's stage set up to optimise (``StageJob``), and what a stage reports back (``StageResult``)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from ops.engine.guided_task import GuidedTask
from ops.engine.loop import LoopConfig, LoopResult, run_loop
from ops.engine.progress import ProgressFn


@dataclass
class StageResult:
    """What a stage reports back: metrics for the manifest, notes for people, the prior used."""

    metrics: dict[str, Any]
    prior: str
    device: str
    notes: list[str] = field(default_factory=list)


def loop_metrics(result: LoopResult) -> dict[str, Any]:
    last = result.history[-1] if result.history else {}
    out: dict[str, Any] = {"steps_run": result.steps_run, "resumed_from_step": result.resumed_from,
                           "loop_wall_s": round(result.wall_s, 3)}
    out.update({f"guard_{k}": v for k, v in result.guards.as_dict().items()})
    if "ref_psnr" in last:
        out["ref_psnr"] = last["ref_psnr"]
    out["schedule_steps"] = result.schedule_steps
    out["stopped_early"] = result.stopped_at is not None
    out["steps_saved"] = 0 if result.stopped_at is None else result.schedule_steps - result.stopped_at
    return out


def loop_notes(result: LoopResult, loop: LoopConfig) -> list[str]:
    """What people should know about how the loop ended."""
    if result.stopped_at is None:
        return []
    sides = " and the held-out side views moved no more coherently than a random walk" \
        if loop.early_stop_watch_sides else ""
    return [f"stopped at step {result.stopped_at:,} of {result.schedule_steps:,}: the reference-view PSNR gained "
            f"less than {loop.early_stop_min_gain_db:g} dB over the last {loop.early_stop_patience:.0%} of the "
            f"schedule{sides} (--set <stage>.loop.early_stop=false runs every step)"]


@dataclass
class StageJob:
    """One object's stage, set up and ready to optimise: alone (``run``) or in a batch (``run_jobs``).

    ``finish`` writes the stage's outputs from the loop's result; ``close`` releases the object's
    prior state (adapters, cached references) whatever happened."""

    stage: str
    task: GuidedTask
    generator: torch.Generator
    loop: LoopConfig
    finish: Callable[[LoopResult], StageResult]
    close: Callable[[], None]

    def run(self, checkpoint_dir: Path | None = None, progress: ProgressFn | None = None) -> StageResult:
        try:
            looped = run_loop(self.task, self.loop, self.generator, self.stage, checkpoint_dir, progress)
            result = self.finish(looped)
            result.metrics["batch_size"] = 1  # every optimising manifest says how many photos shared its steps
            result.notes.extend(loop_notes(looped, self.loop))
            return result
        finally:
            self.close()
