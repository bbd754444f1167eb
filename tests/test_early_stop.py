"""Early stopping (``ops.engine.early_stop``): the rule, the loop's stop and its exact resume, per-object
stops in a batch, and fingerprints under which a whole-schedule output stays fresh."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from assets_store.hashing import config_hash
from assets_store.runlog import read_runlog
from assets_store.store import Store
from morpheus_core.cameras import reference_camera
from ops.engine.batch import BatchTask
from ops.engine.config_tree import to_dict
from ops.engine.early_stop import EARLY_STOP_FIELDS, SIDES_METRIC, SideWatch, converged, whole_schedule_record
from ops.engine.guided_task import RenderedStep
from ops.engine.loop import LoopConfig, run_loop
from ops.pipeline.runner import Pipeline, stages_until
from ops.reporting.run_table import steps_run
from tests.pipeline_helpers import PHOTOS, manifest, tiny_config
from tests.test_optimise import Regression

LOOP = LoopConfig(100, log_every=5, early_stop=True, early_stop_patience=0.2, early_stop_min_share=0.5,
                  early_stop_min_gain_db=0.1)


def _history(values: list[float], every: int = 5, metric: str = "ref_psnr") -> list[dict[str, Any]]:
    return [{"step": every * (i + 1), metric: v} for i, v in enumerate(values)]


def test_a_plateau_stops_and_progress_goes_on() -> None:
    rng = np.random.default_rng()
    rising = list(np.cumsum(rng.uniform(0.2, 1.0, 20)) + 10)  # ≥ 0.2 dB per row: always improving
    assert not any(converged(_history(rising[:n]), 5 * n, LOOP) for n in range(1, 21))
    flat = list(20 + rng.uniform(-0.04, 0.04, 20))  # noise below the gain: converged once allowed
    decisions = [converged(_history(flat[:n]), 5 * n, LOOP) for n in range(1, 20)]
    assert decisions.index(True) == 9  # first asked at step 50 = min_share · steps
    assert not converged(_history(flat), 100, LOOP)  # the last step: nothing left to save
    assert not converged(_history(flat[:12]), 60, replace(LOOP, early_stop=False))


def test_the_window_compares_best_values_and_skips_non_finite_rows() -> None:
    # One good row inside the window is progress even when the last row is worse.
    values = [20.0] * 12
    values[10] = 21.0
    assert not converged(_history(values), 60, LOOP)
    values[10] = float("nan")
    assert converged(_history(values), 60, LOOP)
    assert not converged(_history([float("nan")] * 12), 60, LOOP)  # nothing to compare: go on


def test_settings_outside_their_range_are_refused() -> None:
    for bad in ({"early_stop_patience": 0.0}, {"early_stop_min_share": 1.5}, {"early_stop_min_gain_db": -1.0},
                {"early_stop_min_gain_db": float("inf")}):
        with pytest.raises(ValueError, match="early_stop"):
            LoopConfig(10, **bad)


def _regression_loop(ckpt: Path | None, early_stop: bool = True, kill_at: int | None = None) -> Any:
    task = Regression(11, {kill_at: "kill"} if kill_at is not None else None)
    cfg = LoopConfig(400, checkpoint_every=20, log_every=5, grad_clip=None, early_stop=early_stop,
                     early_stop_patience=0.1, early_stop_min_share=0.25, early_stop_min_gain_db=0.5)
    return task, run_loop(task, cfg, torch.Generator().manual_seed(4), "test", ckpt)


def test_the_loop_stops_early_on_the_same_path_as_the_fixed_schedule() -> None:
    _, res = _regression_loop(None)
    _, fixed = _regression_loop(None, early_stop=False)
    assert res.stopped_at is not None and 100 <= res.stopped_at < 400
    assert res.steps_run == res.stopped_at and res.schedule_steps == 400
    assert fixed.stopped_at is None and fixed.steps_run == 400
    assert res.history[-1]["step"] == res.stopped_at
    assert res.history == [{**r, "wall_s": h["wall_s"]} for r, h in zip(fixed.history, res.history, strict=False)]
    assert fixed.history[-1]["fit_db"] - res.history[-1]["fit_db"] < 2.0  # it had converged


class _Kill(RuntimeError):
    pass


def test_a_run_killed_before_its_stop_resumes_to_the_same_stop(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    task, whole = _regression_loop(None)
    assert whole.stopped_at is not None
    kill = whole.stopped_at - 7
    original = Regression.step

    def step(self: Regression, step: int, generator: torch.Generator) -> Any:
        if self.poison.get(step) == "kill":
            raise _Kill(f"killed at {step}")
        return original(self, step, generator)

    monkeypatch.setattr(Regression, "step", step)
    with pytest.raises(_Kill):
        _regression_loop(tmp_path, kill_at=kill)
    resumed_task, resumed = _regression_loop(tmp_path)
    assert resumed.resumed_from is not None and resumed.resumed_from < kill
    assert resumed.stopped_at == whole.stopped_at
    for a, b in zip(task.net.parameters(), resumed_task.net.parameters(), strict=True):
        assert torch.equal(a, b)


class _StubTask:
    """Just enough of a ``GuidedTask`` for ``BatchTask``'s bookkeeping of stopped objects."""

    guidance = None

    def __init__(self) -> None:
        self.renders = 0

    def render_step(self, step: int, generator: torch.Generator) -> RenderedStep:
        self.renders += 1
        image = torch.rand(1, 3, 4, 4)
        return RenderedStep(None, image, image, torch.zeros(()))  # type: ignore[arg-type]

    def stop_early(self, history: list[dict[str, Any]], done: int, config: LoopConfig, prefix: str) -> bool:
        return converged(history, done, config, prefix + "ref_psnr")

    def evaluate(self, done: int) -> dict[str, float]:
        return {"ref_psnr": 1.0}

    def state(self) -> dict[str, Any]:
        return {"renders": self.renders}

    def load_state(self, state: dict[str, Any]) -> None:
        self.renders = state["renders"]


def test_a_batch_stops_each_object_on_its_own_log_and_ends_when_all_have() -> None:
    tasks = [_StubTask(), _StubTask()]
    batch = BatchTask(tasks, [torch.Generator(), torch.Generator()])  # type: ignore[list-item]
    assert [t.shared_by for t in tasks] == [2, 2]  # the tasks know they share their steps
    flat, rising = [20.0] * 12, [20.0 + i for i in range(12)]
    history = [{"step": 5 * (i + 1), "0/ref_psnr": f, "1/ref_psnr": r}
               for i, (f, r) in enumerate(zip(flat, rising, strict=True))]
    assert not batch.stop_early(history, 60, LOOP)
    assert batch.stopped == {0: 60}
    assert set(batch.evaluate(60)) == {"1/ref_psnr"}
    live, _ = batch._render_all(61)
    assert live == [1] and (tasks[0].renders, tasks[1].renders) == (0, 1)
    # A restore of an older state keeps the stop; a later plateau of the other object ends the batch.
    older = {**batch.state(), "stopped": {}}
    batch.load_state(older)
    assert batch.stopped == {0: 60}
    history += [{"step": 65, "1/ref_psnr": 31.0}, {"step": 70, "1/ref_psnr": 31.0}, {"step": 75, "1/ref_psnr": 31.0},
                {"step": 80, "1/ref_psnr": 31.0}, {"step": 85, "1/ref_psnr": 31.0}]
    assert batch.stop_early(history, 85, LOOP)
    assert batch.stopped == {0: 60, 1: 85}


def test_whole_schedule_records_drop_only_the_early_stop_settings() -> None:
    cfg = tiny_config()
    record = to_dict({"dmtet": cfg.dmtet, "priors": cfg.priors})
    whole = whole_schedule_record(record)
    assert set(record["dmtet"]["loop"]) - set(whole["dmtet"]["loop"]) == set(EARLY_STOP_FIELDS)
    assert whole["dmtet"]["loop"]["steps"] == cfg.dmtet.loop.steps and whole["priors"] == record["priors"]
    other = to_dict({"dmtet": replace(cfg.dmtet, loop=replace(cfg.dmtet.loop, early_stop=False)), "priors": cfg.priors})
    assert config_hash(whole_schedule_record(other)) == config_hash(whole) != config_hash(other)


# The reference-view rule alone, set to stop at the first row it may.
FORCE_STOP = ("early_stop=true", "early_stop_min_share=0", "early_stop_patience=0.01", "early_stop_min_gain_db=1000",
              "early_stop_watch_sides=false")


HOLD_LEVELS = "nerf.model.grid.update_steps=100"  # the tiny NeRF's last hash-grid levels never switch on


def _forced(stages: tuple[str, ...], *extra: str) -> Any:
    return tiny_config(*[f"{s}.loop.{o}" for s in stages for o in FORCE_STOP], *extra)


def test_stages_stop_early_record_it_and_stay_fresh_only_for_their_settings(tmp_path: Path) -> None:
    store, photo = Store(tmp_path / "store"), PHOTOS / "mug.jpg"
    cfg = _forced(("nerf", "dmtet"), HOLD_LEVELS)
    outcome = Pipeline(store, cfg, "tiny").run([(photo, "mug")], stages_until("dmtet"))[0]
    assert outcome.error is None, outcome.error
    nerf, dmtet = manifest(store, "mug", "nerf"), manifest(store, "mug", "dmtet")
    # The NeRF stage may not stop while its finer hash-grid levels are still switching on.
    assert nerf.metrics["stopped_early"] is False and nerf.metrics["steps_run"] == cfg.nerf.loop.steps
    assert dmtet.metrics["stopped_early"] is True
    assert dmtet.metrics["steps_saved"] == cfg.dmtet.loop.steps - dmtet.metrics["steps_run"] > 0
    assert any("stopped at step" in n for n in dmtet.notes)
    planned = cfg.nerf.loop.steps + cfg.dmtet.loop.steps
    saved = dmtet.metrics["steps_saved"]
    assert steps_run(outcome) == f"{planned - saved}/{planned} (-{saved / planned:.0%})"
    assert Pipeline(store, cfg).status(photo, "mug")["dmtet"] == "fresh"
    fixed = _forced(("nerf",), "dmtet.loop.early_stop=false", HOLD_LEVELS)
    status = Pipeline(store, fixed).status(photo, "mug")
    assert status["nerf"] == "fresh" and status["dmtet"] == "stale"  # it stopped under the settings it no longer has
    nerf_off = tiny_config("nerf.loop.early_stop=false", HOLD_LEVELS)
    assert Pipeline(store, nerf_off).status(photo, "mug")["nerf"] == "fresh"  # the whole schedule satisfies any setting


def test_the_nerf_stage_stops_only_once_every_level_is_on(tmp_path: Path) -> None:
    cfg = _forced(("nerf",))
    grid = cfg.nerf.model.grid
    all_on = next(s for s in range(cfg.nerf.loop.steps) if grid.levels_at(s) == grid.n_levels)
    assert 0 < all_on < cfg.nerf.loop.steps - 1  # the shortened schedule switches every level on
    pipeline = Pipeline(Store(tmp_path / "store"), cfg, "tiny")
    outcome = pipeline.run([(PHOTOS / "mug.jpg", "mug")], stages_until("nerf"))[0]
    assert outcome.error is None, outcome.error
    nerf = manifest(Store(tmp_path / "store"), "mug", "nerf")
    assert nerf.metrics["stopped_early"] is True and all_on <= nerf.metrics["steps_run"] < cfg.nerf.loop.steps


def test_a_batch_records_each_object_s_stop(tmp_path: Path) -> None:
    store, cfg = Store(tmp_path / "store"), _forced(("dmtet",))
    photos = [(PHOTOS / "mug.jpg", "mug"), (PHOTOS / "box.jpg", "box")]
    outcomes = Pipeline(store, cfg, "tiny").run(photos, stages_until("dmtet"))
    assert all(o.error is None for o in outcomes), [o.error for o in outcomes]
    for _, key in photos:
        m = manifest(store, key, "dmtet")
        assert m.metrics["batch_size"] == 2 and m.metrics["stopped_early"] is True
        assert m.metrics["steps_run"] + m.metrics["steps_saved"] == cfg.dmtet.loop.steps


def _watch_drifts(frames: list[torch.Tensor], window: int = 4) -> list[float]:
    watch = SideWatch(window, reference_camera())
    return [watch.observe(i + 1, f)[SIDES_METRIC] for i, f in enumerate(frames)]


def test_the_side_watch_tells_drift_from_a_random_walk_from_settled_jitter() -> None:
    g = torch.Generator().manual_seed(int(np.random.default_rng().integers(1 << 30)))
    shape, n = (3, 3, 64, 64), 4  # four log intervals per window
    start, direction = torch.rand(shape, generator=g), torch.randn(shape, generator=g) * 0.01
    drifting = [start + i * direction + 1e-4 * torch.randn(shape, generator=g) for i in range(12)]
    walk = [start]
    for _ in range(11):
        walk.append(walk[-1] + 0.01 * torch.randn(shape, generator=g))
    settled = [start + 0.01 * torch.randn(shape, generator=g) for _ in range(12)]
    for frames, lo, hi in ((drifting, 0.9 * n, 1.1 * n), (walk, 0.8, 1.2), (settled, 0.8 / n, 1.2 / n)):
        drifts = _watch_drifts(frames, n)
        assert all(np.isnan(drifts[:n]))  # fewer than a window of intervals: nothing to say yet
        assert all(lo < d < hi for d in drifts[n:]), drifts
    frozen = _watch_drifts([start] * 8, n)
    assert frozen[n:] == [0.0] * (8 - n)  # renders that no longer change at all have settled
    nan = start.clone()
    nan[0, 0, 0, 0] = float("nan")
    assert np.isnan(SideWatch(n, reference_camera()).observe(1, nan)[SIDES_METRIC])


def test_the_side_watch_keeps_one_window_and_resumes_from_its_state() -> None:
    g = torch.Generator().manual_seed(int(np.random.default_rng().integers(1 << 30)))
    frames = [torch.rand(3, 3, 8, 8, generator=g) for _ in range(10)]
    whole = SideWatch(6, reference_camera())
    expected = [whole.observe(3 * (i + 1), f) for i, f in enumerate(frames)]
    assert len(whole.rows) == 3  # the anchor at or before the window's start and the rows after it
    first = SideWatch(6, reference_camera())
    for i, f in enumerate(frames[:5]):
        first.observe(3 * (i + 1), f)
    resumed = SideWatch(6, reference_camera())
    resumed.load_state(first.state())
    assert [resumed.observe(3 * (i + 6), f) for i, f in enumerate(frames[5:])] == expected[5:]


def test_the_reference_rule_waits_for_the_sides_when_they_are_watched() -> None:
    history = _history([20.0] * 12)  # the reference view has plateaued
    for drift, stops in ((3.5, False), (1.0, True), (0.3, True), (float("nan"), False)):
        rows = [*history[:-1], {**history[-1], "3/" + SIDES_METRIC: drift}]
        assert converged(rows, 60, LOOP, "ref_psnr", "3/" + SIDES_METRIC) is stops
    assert not converged(history, 60, LOOP, "ref_psnr", SIDES_METRIC)  # no column: not known to have settled
    assert converged(history, 60, replace(LOOP, early_stop_watch_sides=False), "ref_psnr", SIDES_METRIC)
    assert converged(history, 60, LOOP, "ref_psnr", None)  # a task without side views: the reference decides


@pytest.mark.parametrize("frozen", [False, True])
def test_a_stage_watching_its_sides_stops_at_the_first_row_they_have_settled(tmp_path: Path, frozen: bool) -> None:
    """The reference rule is set to agree at every row: the side views decide. Learning rates of 0 freeze the
    mesh, so its sides settle as soon as the window has filled; trained, they still drift in the tiny run."""
    watch = ("early_stop=true", "early_stop_min_share=0", "early_stop_patience=0.5", "early_stop_min_gain_db=1000")
    still = [f"dmtet.{lr}=0" for lr in ("lr_sdf", "lr_deform", "lr_grid", "lr_mlp")] if frozen else []
    cfg = tiny_config(*[f"dmtet.loop.{o}" for o in watch], *still, dmtet=16)
    store = Store(tmp_path / "store")
    outcome = Pipeline(store, cfg, "tiny").run([(PHOTOS / "mug.jpg", "mug")], stages_until("dmtet"))[0]
    assert outcome.error is None, outcome.error
    rows = read_runlog(store.stage_dir("mug", "dmtet") / "runlog.parquet")
    window = round(0.5 * cfg.dmtet.loop.steps)
    assert all(r[SIDES_METRIC] is None for r in rows if r["step"] < rows[0]["step"] + window)  # no anchor yet
    assert all(r["sides_change"] is not None for r in rows[1:])
    settled = [r["step"] for r in rows if r[SIDES_METRIC] is not None and r[SIDES_METRIC] <= 1.0
               and r["step"] < cfg.dmtet.loop.steps]
    m = manifest(store, "mug", "dmtet")
    assert m.metrics["stopped_early"] is bool(settled) is frozen
    assert m.metrics["steps_run"] == (settled[0] if settled else cfg.dmtet.loop.steps)
    assert rows[-1]["step"] == m.metrics["steps_run"]
    if frozen:
        assert rows[-1][SIDES_METRIC] == 0.0 and any("side views" in n for n in m.notes)


def test_a_stage_killed_while_watching_its_sides_resumes_to_the_same_stop(tmp_path: Path,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """The held-out renders of the window travel in the checkpoint: without them the resumed run would have no
    anchor for the window and stop later. Frozen learning rates make the uninterrupted stop come at the first row
    with a full window (step 9 of 16: rows every 2 steps from 1, a window of 8)."""
    from ops.stages.dmtet import DMTetTask

    watch = ("early_stop=true", "early_stop_min_share=0", "early_stop_patience=0.5", "early_stop_min_gain_db=1000")
    still = [f"dmtet.{lr}=0" for lr in ("lr_sdf", "lr_deform", "lr_grid", "lr_mlp")]
    cfg = tiny_config(*[f"dmtet.loop.{o}" for o in watch], *still, dmtet=16)
    assert (cfg.dmtet.loop.log_every, cfg.dmtet.loop.checkpoint_every) == (2, 4)
    whole_store, store = Store(tmp_path / "whole"), Store(tmp_path / "killed")
    assert Pipeline(whole_store, cfg, "tiny").run([(PHOTOS / "mug.jpg", "mug")], stages_until("dmtet"))[0].error is None
    original = DMTetTask.render_step

    def killed_at_6(self: DMTetTask, step: int, generator: torch.Generator) -> RenderedStep:
        if step == 6:
            raise _Kill("killed at step 6, after the checkpoint of step 4")
        return original(self, step, generator)

    monkeypatch.setattr(DMTetTask, "render_step", killed_at_6)
    outcome = Pipeline(store, cfg, "tiny").run([(PHOTOS / "mug.jpg", "mug")], stages_until("dmtet"))[0]
    assert outcome.error is not None and "killed at step 6" in outcome.error
    monkeypatch.setattr(DMTetTask, "render_step", original)
    assert Pipeline(store, cfg, "tiny").run([(PHOTOS / "mug.jpg", "mug")], stages_until("dmtet"))[0].error is None
    whole, resumed = manifest(whole_store, "mug", "dmtet"), manifest(store, "mug", "dmtet")
    assert resumed.metrics["resumed_from_step"] == 4
    assert whole.metrics["steps_run"] == 9 and resumed.metrics["stopped_early"] is True
    assert resumed.metrics["steps_run"] + resumed.metrics["resumed_from_step"] == 9
    logs = [read_runlog(s.stage_dir("mug", "dmtet") / "runlog.parquet") for s in (whole_store, store)]
    assert [(r["step"], r[SIDES_METRIC]) for r in logs[0]] == [(r["step"], r[SIDES_METRIC]) for r in logs[1]]
