"""Honest, visible progress: heartbeats during calls that cannot report, real elapsed times."""

from __future__ import annotations

import io
import threading
import time
from pathlib import Path

import pytest
import torch

import ops.engine.progress as progress_module
import ops.stages.dmtet as dmtet_stage
import ops.stages.qa as qa_stage
from assets_store.store import Store
from ops.engine.checks import QAReport
from ops.engine.loop import LoopConfig, StepOutput, run_loop
from ops.engine.progress import Heartbeat, ProgressEvent
from ops.engine.stage_job import StageResult
from ops.pipeline.runner import Pipeline, stages_until
from ops.reporting.progress import ConsoleProgress, format_event
from tests.pipeline_helpers import PHOTOS, tiny_config
from tests.test_optimise import Regression

BEAT = 0.05  # seconds between heartbeats in these tests (10 s in a run)


class Events(list[ProgressEvent]):
    """A ``ProgressFn`` keeping every event (called from the heartbeat's thread too)."""

    def __call__(self, event: ProgressEvent) -> None:
        self.append(event)


def slow_call(seconds: float = 0.4) -> str:
    """A long library call that cannot report."""
    time.sleep(seconds)
    return "done"


def test_heartbeat_reports_a_silent_call_with_its_real_elapsed_time() -> None:
    events = Events()
    with Heartbeat(events, "mug:dmtet", phase="converting NeRF → DMTet", every_s=BEAT, announce=True):
        assert slow_call() == "done"
    assert events[0].stage == "mug:dmtet (converting NeRF → DMTet)" and events[0].elapsed_s < BEAT  # announced
    beats = events[1:]
    assert len(beats) >= 3, events
    assert all(e.total == 0 and e.stage == events[0].stage for e in beats)
    elapsed = [e.elapsed_s for e in beats]
    assert elapsed == sorted(elapsed) and elapsed[0] >= BEAT * 0.9 and elapsed[-1] <= 0.4 + 2 * BEAT
    count = len(events)
    time.sleep(3 * BEAT)
    assert len(events) == count  # it stops with the call
    assert format_event(beats[-1]).endswith(f"running, {beats[-1].elapsed_s:.0f} s so far")


def test_heartbeat_follows_the_phase_and_stays_quiet_without_a_reporter() -> None:
    events = Events()
    with Heartbeat(events, "qa", every_s=10.0, announce=True) as beat:
        beat.set_phase("reference view")
        beat.set_phase("turntable")
    assert [e.stage for e in events] == ["qa (reference view)", "qa (turntable)"]
    with Heartbeat(None, "qa", every_s=BEAT) as beat:
        slow_call(2 * BEAT)
    assert beat.beats == 0 and not [t for t in threading.enumerate() if t.name.startswith("heartbeat ")]


def test_a_reporter_error_on_the_timer_thread_surfaces_in_the_work() -> None:
    def broken(event: ProgressEvent) -> None:
        raise RuntimeError("the machine went away")

    with pytest.raises(RuntimeError, match="went away"), Heartbeat(broken, "nerf", every_s=BEAT):
        slow_call(4 * BEAT)
    with pytest.raises(ValueError, match="own error wins"), Heartbeat(broken, "nerf", every_s=BEAT):
        slow_call(4 * BEAT)
        raise ValueError("the work's own error wins")


class SlowSteps(Regression):
    def step(self, step: int, generator: torch.Generator) -> StepOutput:
        time.sleep(0.02)
        return super().step(step, generator)


def test_the_loop_reports_between_sparse_log_rows() -> None:
    events = Events()
    cfg = LoopConfig(20, checkpoint_every=100, log_every=100, grad_clip=None)  # log rows at steps 1 and 20 only
    run_loop(SlowSteps(0), cfg, torch.Generator().manual_seed(0), "nerf", None, events, heartbeat_s=BEAT)
    rows = [e for e in events if e.metrics]
    beats = [e for e in events if not e.metrics]
    assert [e.step for e in rows] == [1, 20]
    assert len(beats) >= 3 and all(e.stage == "nerf" and e.total == 20 for e in beats)
    assert any(1 < e.step < 20 for e in beats)  # the step reached, not the last log row's
    for kind in (rows, beats):  # (the two threads' events may cross by microseconds)
        assert [e.elapsed_s for e in kind] == sorted(e.elapsed_s for e in kind)


def test_console_prints_heartbeats_and_at_least_every_interval_off_a_terminal() -> None:
    clock = [0.0]
    out = io.StringIO()
    console = ConsoleProgress(out, every_s=10.0, clock=lambda: clock[0])
    for step in range(1, 5):  # four log rows within the same tenth, 4 s apart
        clock[0] = 4.0 * step
        console(ProgressEvent("mug:nerf", step, 100, clock[0], {"loss": 1.0}))
    console(ProgressEvent("mug:dmtet (converting NeRF → DMTet)", 0, 0, 40.0, {}))
    console(ProgressEvent("mug:dmtet:ran", 1, 1, 312.5, {}))
    lines = out.getvalue().splitlines()
    assert [line.split()[1] for line in lines[:2]] == ["1/100", "4/100"]  # the first, then 12 s later
    assert lines[2].endswith("running, 40 s so far") and "312.5s" in lines[3]


def test_the_stage_outcome_reports_its_wall_time_and_the_conversion_beats(tmp_path: Path,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    real_convert = dmtet_stage.convert

    def slow_convert(*args, **kwargs):  # type: ignore[no-untyped-def]
        time.sleep(0.3)  # what a 128³ grid costs on two CPU cores, shortened
        return real_convert(*args, **kwargs)

    monkeypatch.setattr(progress_module, "HEARTBEAT_S", BEAT)
    monkeypatch.setattr(dmtet_stage, "convert", slow_convert)
    events = Events()
    pipeline = Pipeline(Store(tmp_path), tiny_config(nerf=2, dmtet=1), "tiny", progress=events)
    out = pipeline.run([(PHOTOS / "mug.jpg", "mug.jpg")], stages_until("dmtet"))[0]
    assert out.error is None, out.error
    converting = [e for e in events if e.stage.startswith("mug.jpg:dmtet (converting NeRF → DMTet")]
    assert len(converting) >= 3 and converting[-1].elapsed_s >= 0.25
    assert any(e.stage.startswith("mug.jpg:dmtet (fitting the texture field") for e in events)
    ran = {e.stage: e.elapsed_s for e in events if e.stage.endswith(":ran")}
    walls = {f"mug.jpg:{s.stage}:ran": s.wall_s for s in out.stages}
    assert ran == walls and ran["mug.jpg:dmtet:ran"] >= 0.3  # not 0.0 after a long stage


def test_qa_announces_its_measurements_and_beats(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    def slow_qa(*args, phase, **kwargs) -> tuple[StageResult, QAReport]:  # type: ignore[no-untyped-def]
        phase("turntable views")
        slow_call(0.3)
        return StageResult({"verdict": "pass"}, "none (qa)", "cpu"), QAReport("pass", [], {}, {}, "proxy")

    class Context:  # what the qa stage's body reads of a photo's run
        device = "cpu"
        stages = ("reference", "bake", "qa")
        key = "mug.jpg"

        def dir(self, stage: str) -> Path:
            return tmp_path / stage

        def upstream(self, stage: str) -> object:
            return type("M", (), {"metrics": {}, "prior": "proxy"})()

        def stage_checks(self, stage: str, thresholds: object) -> list:
            return []

        def progress(self) -> Events:
            return events

    monkeypatch.setattr(progress_module, "HEARTBEAT_S", BEAT)
    monkeypatch.setattr(qa_stage, "run_qa", lambda *a, **k: slow_qa(*a, phase=a[-1]))
    events = Events()
    result = qa_stage.STAGE.build(Context(), tiny_config().qa).body(tmp_path / "qa", None)  # type: ignore[arg-type]
    assert result.metrics["verdict"] == "pass"
    assert events[0].stage == "qa (turntable views)" and len(events) >= 4
