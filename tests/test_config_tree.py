"""Presets and overrides: every key reachable, types checked, ablations expressible as settings."""

from __future__ import annotations

import json

import pytest

from morpheus_core.guidance.frequency import BandMask
from morpheus_core.guidance.presets import PAPER_ROWS, paper_ablations
from ops.config.presets import PRESETS, PipelineConfig, preset, scaled_levels, with_steps
from ops.engine.config_tree import ConfigError, apply_overrides, flat_keys, from_dict, to_dict


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_presets_round_trip_through_plain_data(name: str) -> None:
    cfg = preset(name)
    assert from_dict(PipelineConfig, to_dict(cfg)) == cfg


def test_paper_preset_holds_the_papers_schedule() -> None:
    cfg = preset("paper")
    assert (cfg.nerf.loop.steps, cfg.dmtet.loop.steps, cfg.texture.loop.steps) == (10_000, 5000, 5000)
    assert (cfg.nerf.resolution, cfg.dmtet.resolution, cfg.texture.resolution) == (128, 512, 512)
    assert cfg.nerf.render.n_samples == 256 and cfg.dmtet.max_grid == 128
    g = cfg.texture.guidance.build(cfg.texture.loop.steps)
    assert g.lambda_c == 5e-4 and [t.mode for t in g.terms] == ["sds", "vsd"]
    assert g.terms[1].filters[0].band == BandMask.high_pass(0.6) and g.terms[1].filters[0].k == 3.0
    assert g.terms[0].cfg_scale == 3.0 and g.terms[1].cfg_scale == 2.0 and g.terms[1].finetuned_cfg_scale == 1.0
    t = cfg.nerf.guidance.t_range(cfg.nerf.loop.steps)
    assert t.bounds(0) == (0.02, 0.98) and t.bounds(5000) == (0.02, 0.5)


@pytest.mark.parametrize("steps", [1000, 500, 150, 37])
def test_shortened_schedules_keep_the_level_schedule_shape(steps: int) -> None:
    paper = preset("paper").nerf.model.grid
    grid = with_steps(preset("paper"), steps, 10, 10).nerf.model.grid
    full = next(s for s in range(10_001) if paper.levels_at(s) == paper.n_levels)
    assert full == 6000  # threestudio's: 8 of 16 levels, one more every 500 steps from step 2000
    short_full = next(s for s in range(steps + 1) if grid.levels_at(s) == grid.n_levels)
    # all levels on at 60 % of the shortened run too, up to the rounding of one update interval
    assert abs(short_full - 0.6 * steps) <= 8 * max(1, round(500 * steps / 10_000)) / 2 + 1
    assert grid.levels_at(0) == paper.levels_at(0) == 8
    assert (grid.n_levels, grid.log2_table_size) == (paper.n_levels, paper.log2_table_size)


def test_level_schedule_factor_must_be_positive() -> None:
    grid = preset("paper").nerf.model.grid
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="schedule factor"):
            scaled_levels(grid, bad)
    assert scaled_levels(grid, 1.0) == grid


def test_overrides_are_typed_and_checked() -> None:
    cfg = preset("draft", ["nerf.loop.steps=7", "texture.guidance.r=0.4", "priors.kind=proxy", "seed=3",
                           "dmtet.grid=32", "dmtet.grid=null", "bake.write_obj=false"])
    assert cfg.nerf.loop.steps == 7 and cfg.texture.guidance.r == 0.4 and cfg.priors.kind == "proxy"
    assert cfg.seed == 3 and cfg.dmtet.grid is None and cfg.bake.write_obj is False
    for bad in ["nerf.loop.stepz=3", "nerf.loop.steps=many", "priors.kind=magic", "texture.guidance.r=2",
                "nerf=3", "noequals", "nerf.loop.steps=1.5", "bake.write_obj=1"]:
        with pytest.raises(ConfigError):
            apply_overrides(cfg, [bad])


def test_a_star_segment_sets_the_key_in_every_group() -> None:
    cfg = preset("draft", ["*.loop.early_stop=true", "*.loop.early_stop_min_share=0.7"])
    assert [s.loop.early_stop for s in (cfg.nerf, cfg.dmtet, cfg.texture)] == [True, True, True]
    assert {s.loop.early_stop_min_share for s in (cfg.nerf, cfg.dmtet, cfg.texture)} == {0.7}
    assert preset("draft", ["nerf.loop.early_stop=true"]).dmtet.loop.early_stop is False
    for bad in ["*.loop.no_such_key=1", "*.*.*.*.*.*.*.*=1", "*.loop.early_stop=maybe"]:
        with pytest.raises(ConfigError):
            apply_overrides(cfg, [bad])


def test_every_leaf_key_is_overridable() -> None:
    cfg = preset("draft")
    keys = flat_keys(cfg)
    assert "texture.guidance.k2d" in keys and "nerf.model.grid.n_levels" in keys
    assert len(keys) == len(set(keys)) > 60


def test_every_paper_ablation_row_is_a_setting() -> None:
    """Each stage-2 row of the paper is reachable by ``--set`` overrides alone, and builds the row's terms."""
    expected = paper_ablations()
    assert set(PAPER_ROWS) == set(expected) and len(expected) == 17
    for name, change in PAPER_ROWS.items():
        sets = [f"texture.guidance.{k}={json.dumps(v)}" for k, v in change.items()]
        built = preset("paper", sets).texture.guidance.build(5000)
        # A term whose every filter has k = 0 or the null band adds nothing; the settings leave it out.
        want = [t for t in expected[name].terms if any(f.k > 0 and f.band.kind != "null" for f in t.filters)]
        assert [(t.prior, t.mode, t.filters, t.cfg_scale) for t in built.terms] == \
               [(t.prior, t.mode, t.filters, t.cfg_scale) for t in want], name

