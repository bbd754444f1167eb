"""``benchmarks/paper_speed.py``'s arithmetic: each render phase timed and extrapolated to its own steps."""

from __future__ import annotations

import random

import pytest

from benchmarks.paper_speed import STAGES, phase_config, phase_steps, projections
from ops.config.presets import preset
from tests.seeds import fresh_seed


def test_phase_steps_cover_the_schedule_and_phase_config_renders_one_phase() -> None:
    cfg = preset("fast")
    for stage in STAGES:
        parts = phase_steps(cfg, stage)
        assert sum(n for _, n in parts) == getattr(cfg, stage).loop.steps
        assert [p for p, _ in parts] == [0, -1]  # one coarse phase, then the final one
        coarse = phase_config(cfg, stage, 0)
        stage_cfg, phase = getattr(coarse, stage), getattr(cfg, stage).phases[0]
        assert stage_cfg.phases == () and (stage_cfg.resolution, stage_cfg.n_views) == (phase.resolution,
                                                                                        phase.n_views)
        final = getattr(phase_config(cfg, stage, -1), stage)
        assert final.resolution == getattr(cfg, stage).resolution and final.phases == ()
    assert phase_steps(preset("paper"), "nerf") == [(-1, 10_000)]


def test_projections_sum_each_phase_at_its_own_rate() -> None:
    rng = random.Random(fresh_seed())
    cfg = preset("fast")
    schedule = {s: phase_steps(cfg, s) for s in STAGES}
    rows, expected = [], 0.0
    for stage in STAGES:
        for phase, steps in schedule[stage]:
            ms, setup = rng.uniform(10, 300), rng.uniform(0, 30)
            rows.append({"stage": stage, "batch": 1, "phase": phase, "ms_per_step": ms, "setup_s_per_object": setup,
                         "peak_gib": 1.0})
            expected += ms * steps / 60000 + (setup / 60 if phase == -1 else 0.0)
    (proj,) = projections(rows, schedule)
    assert proj["min_per_object"] == pytest.approx(expected, abs=0.02)
    assert projections(rows[:-1], schedule) == []  # a phase not timed: no projection
