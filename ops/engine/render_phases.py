"""Coarse-to-fine render phases of an optimising stage: what each step renders.

A stage's config names its final render size and views per step (``resolution``, ``n_views``:
the paper's one view at full size) and optionally coarser ``phases`` before them. A phase holds
while the step is below ``until`` × the stage's steps; the stage's own settings hold after the
last one. Fractions, not step counts, so a shortened schedule (``ops.config.presets.with_steps``,
the benchmarks' ``paper/10``) keeps its shape.

Why: early in a stage the object is blurry, the prior's gradient is mostly noise, and a render
at full size mainly costs time; several smaller views per step average that noise away for the
same pixels (threestudio's Stable Zero123 recipe: 64 → 128 → 256 px with 12 → 8 → 4 views).
The guidance averages over a step's views, so λc, k3D, k2D and σ keep their meaning.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol


@dataclass(frozen=True)
class Phase:
    """One coarse phase: while step < ``until`` × steps, render ``n_views`` views at ``resolution`` px."""

    until: float
    """End of the phase as a fraction of the stage's steps (0 < until < 1)."""
    resolution: int
    """Render size (px) of the reference and novel views in this phase."""
    n_views: int = 1
    """Random orbit views per step in this phase."""

    def __post_init__(self) -> None:
        if not 0.0 < self.until < 1.0:
            raise ValueError(f"a phase's until must be a fraction in (0, 1), got {self.until}")
        if self.resolution < 8 or self.n_views < 1:
            raise ValueError(f"a phase needs resolution ≥ 8 and n_views ≥ 1, got {self.resolution} and {self.n_views}")


def check_phases(phases: Sequence[Phase]) -> None:
    """Phases must end in increasing order (``ValueError`` otherwise)."""
    ends = [p.until for p in phases]
    if any(b <= a for a, b in itertools.pairwise(ends)):
        raise ValueError(f"phases must end in increasing order, got until = {ends}")


@dataclass(frozen=True)
class StepShape:
    """What one step renders: ``n_views`` novel views and the reference view at ``resolution`` px,
    in phase ``index`` (``final`` for the stage's own settings, after every coarse phase)."""

    resolution: int
    n_views: int
    index: int
    final: bool


class _Loop(Protocol):
    @property
    def steps(self) -> int: ...


class PhasedStageConfig(Protocol):
    """What an optimising stage's config says about its renders (``NerfStageConfig`` and the others)."""

    @property
    def phases(self) -> tuple[Phase, ...]: ...

    @property
    def resolution(self) -> int: ...

    @property
    def n_views(self) -> int: ...

    @property
    def loop(self) -> _Loop: ...


@dataclass(frozen=True)
class RenderSchedule:
    """A stage's phases over its ``steps`` steps, ending at ``resolution`` and ``n_views``."""

    phases: tuple[Phase, ...]
    resolution: int
    n_views: int
    steps: int

    def __post_init__(self) -> None:
        check_phases(self.phases)

    @classmethod
    def of(cls, cfg: PhasedStageConfig) -> RenderSchedule:
        return cls(tuple(cfg.phases), cfg.resolution, cfg.n_views, cfg.loop.steps)

    def at(self, step: int) -> StepShape:
        """The shape of step ``step`` (0-based)."""
        for i, p in enumerate(self.phases):
            if step < p.until * self.steps:
                return StepShape(p.resolution, p.n_views, i, False)
        return StepShape(self.resolution, self.n_views, len(self.phases), True)

    def final_from(self) -> int:
        """The first step of the final phase (0 without coarse phases)."""
        return min(self.steps, math.ceil(self.phases[-1].until * self.steps)) if self.phases else 0
