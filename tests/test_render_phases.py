"""Coarse-to-fine render phases: the schedule's arithmetic, the config keys, and the stages really
rendering each phase's size and views (and only stopping early in the final phase)."""

from __future__ import annotations

import random
from typing import Any

import pytest
import torch

import ops.engine.guided_task as guided_task
from assets_store.store import Store
from ops.config.presets import preset, with_steps
from ops.engine.config_tree import ConfigError
from ops.engine.render_phases import Phase, RenderSchedule
from ops.engine.target import ReferenceTarget
from ops.pipeline.photo_run import stage_config_record
from ops.pipeline.runner import Pipeline, stages_until
from tests.pipeline_helpers import PHOTOS, tiny_config
from tests.seeds import fresh_seed


def test_each_step_falls_in_the_phase_its_fraction_names() -> None:
    rng = random.Random(fresh_seed())
    steps = rng.randrange(20, 2000)
    a, b = sorted(rng.sample(range(1, 99), 2))
    sched = RenderSchedule((Phase(a / 100, 32, 4), Phase(b / 100, 64, 2)), 128, 1, steps)
    for step in range(steps):
        shape = sched.at(step)
        if step < a / 100 * steps:
            assert (shape.resolution, shape.n_views, shape.index, shape.final) == (32, 4, 0, False)
        elif step < b / 100 * steps:
            assert (shape.resolution, shape.n_views, shape.index, shape.final) == (64, 2, 1, False)
        else:
            assert (shape.resolution, shape.n_views, shape.index, shape.final) == (128, 1, 2, True)
    first_final = sched.final_from()
    assert sched.at(first_final).final and not sched.at(first_final - 1).final
    assert RenderSchedule((), 128, 1, steps).final_from() == 0


def test_a_shortened_schedule_keeps_the_phases_shape() -> None:
    cfg = preset("draft", ['nerf.phases=[{"until": 0.5, "resolution": 24, "n_views": 3}]'])
    for steps in (150, 40, 8):
        short = with_steps(cfg, steps, 10, 10)
        sched = RenderSchedule.of(short.nerf)
        coarse = sum(not sched.at(s).final for s in range(steps))
        assert coarse == pytest.approx(steps / 2, abs=1)


@pytest.mark.parametrize("phases", [
    '[{"until": 1.0, "resolution": 24}]',
    '[{"until": 0.6, "resolution": 24}, {"until": 0.3, "resolution": 32}]',
    '[{"until": 0.5, "resolution": 4}]',
    '[{"until": 0.5, "resolution": 24, "n_views": 0}]',
    '[{"until": 0.5, "size": 24}]',
])
def test_a_bad_phase_is_a_config_error_naming_the_key(phases: str) -> None:
    with pytest.raises(ConfigError, match="phases"):
        preset("draft", [f"texture.phases={phases}"])


def test_no_phases_leaves_the_fingerprints_of_existing_outputs_alone() -> None:
    cfg = preset("draft")
    record = stage_config_record({"nerf": cfg.nerf})
    assert "phases" not in record["nerf"]
    with_phase = preset("draft", ['nerf.phases=[{"until": 0.25, "resolution": 24}]'])
    assert stage_config_record({"nerf": with_phase.nerf})["nerf"]["phases"] == [
        {"until": 0.25, "resolution": 24, "n_views": 1}]


def test_a_resized_target_is_the_photo_at_the_new_size() -> None:
    gen = torch.Generator().manual_seed(fresh_seed())
    rgb = torch.rand(1, 3, 32, 32, generator=gen)
    mask = (torch.rand(1, 1, 32, 32, generator=gen) > 0.5).float()
    target = ReferenceTarget(rgb, mask, camera=None)  # type: ignore[arg-type]
    small = target.resized(16)
    assert small.rgb.shape == (1, 3, 16, 16) and small.mask.shape == (1, 1, 16, 16)
    # Each coarse pixel is the mean of the 2×2 block it covers.
    blocks = rgb.reshape(1, 3, 16, 2, 16, 2).mean(dim=(3, 5))
    torch.testing.assert_close(small.rgb, blocks)
    assert torch.isclose(small.mask.mean(), mask.mean())
    assert target.resized(32) is target


def test_every_stage_renders_its_phases_sizes_and_views(tmp_path: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    """The tiny pipeline with a coarse phase in each optimising stage: the guidance sees the phase's
    views at its size, then the stage's own, and the outputs are finite."""
    phases = {"nerf": (16, 3), "dmtet": (24, 2), "texture": (24, 2)}
    overrides = [f'{s}.phases=[{{"until": 0.5, "resolution": {r}, "n_views": {v}}}]' for s, (r, v) in phases.items()]
    cfg = tiny_config(*overrides, nerf=8, dmtet=6, texture=6)
    seen: list[tuple[int, int, int]] = []
    real = guided_task.hybrid_guidance

    def spy(config: Any, bindings: Any, schedule: Any, novel: torch.Tensor, step: int, reference_render: Any,
            reference: Any, *args: Any, **kwargs: Any) -> Any:
        assert reference.shape[-1] == reference_render.shape[-1] == novel.shape[-1]
        seen.append((step, novel.shape[0], novel.shape[-1]))
        return real(config, bindings, schedule, novel, step, reference_render, reference, *args, **kwargs)

    monkeypatch.setattr(guided_task, "hybrid_guidance", spy)
    outcome = Pipeline(Store(tmp_path), cfg, "draft").run([(PHOTOS / "mug.jpg", "mug.jpg")], stages_until("texture"))[0]
    assert outcome.error is None, outcome.error
    # The stages run in order; split the record where the step counter starts again.
    runs: list[list[tuple[int, int, int]]] = [[]]
    for row in seen:
        if runs[-1] and row[0] < runs[-1][-1][0]:
            runs.append([])
        runs[-1].append(row)
    assert len(runs) == 3
    for (stage, (coarse, views)), run in zip(phases.items(), runs, strict=True):
        final = getattr(cfg, stage).resolution
        steps = getattr(cfg, stage).loop.steps
        for step, n, size in run:
            expected = (views, coarse) if step < 0.5 * steps else (1, final)
            assert (n, size) == expected, (stage, step)
