"""The GPU-sharing benchmark's arithmetic: shares parsed, aggregate rates over processes, a failed
window reported rather than extrapolated."""

from __future__ import annotations

import argparse
import random

import pytest

from benchmarks.gpu_sharing import aggregate, mix_efficiency, parse_mix, parse_share, plan, to_markdown

SCHEDULE = {"nerf": 10_000, "dmtet": 5_000, "texture": 5_000}


def _row(share: str, stage: str, process: int, batch: int, ms: float, setup: float = 1.0) -> dict:
    steps = random.randint(10, 40)
    return {"share": share, "stage": stage, "process": process, "batch": batch, "steps": steps,
            "elapsed_s": steps * ms / 1000, "ms_per_step": ms, "setup_s_per_object": setup,
            "peak_gib": random.uniform(10, 60)}


def test_shares_parse_and_bad_ones_are_named() -> None:
    assert parse_share("3x4") == (3, 4) and parse_share("1X8") == (1, 8)
    for bad in ("3", "0x4", "ax4", "2x-1"):
        with pytest.raises(argparse.ArgumentTypeError, match=r"PROCESSESxBATCH|≥ 1"):
            parse_share(bad)


def test_the_aggregate_rate_adds_the_processes_object_steps() -> None:
    ms = {s: random.uniform(50, 900) for s in SCHEDULE}
    rows = [_row("1x8", s, 0, 8, ms[s]) for s in SCHEDULE]
    slower = {s: random.uniform(1.0, 2.0) for s in SCHEDULE}  # each of 2 processes of 4 is slower
    rows += [_row("2x4", s, k, 4, ms[s] / 2 * slower[s]) for s in SCHEDULE for k in range(2)]
    stages, shares = aggregate(rows, SCHEDULE)
    one = {r["stage"]: r["ms_per_object_step"] for r in stages if r["share"] == "1x8"}
    two = {r["stage"]: r["ms_per_object_step"] for r in stages if r["share"] == "2x4"}
    for s in SCHEDULE:
        assert one[s] == pytest.approx(ms[s] / 8, rel=1e-3)
        # 2 processes × 4 objects / (ms/2·slower) per ms: the same object-steps as 1x8 when slower is 2.
        assert two[s] == pytest.approx(ms[s] / 8 * slower[s] / 2, rel=1e-3)
    gpu_min = {r["share"]: r["gpu_min_per_object"] for r in shares}
    expected = sum(one[s] * SCHEDULE[s] / 60000 for s in SCHEDULE) + 3 * 1.0 / 60
    assert gpu_min["1x8"] == pytest.approx(expected, abs=0.01)
    assert {r["share"]: r["objects_per_gpu_hour"] for r in shares}["1x8"] == pytest.approx(60 / expected, abs=0.01)


def test_a_failed_window_is_reported_not_extrapolated() -> None:
    rows = [_row("1x8", s, 0, 8, 100.0) for s in SCHEDULE]
    rows += [_row("2x8", s, 0, 8, 150.0) for s in SCHEDULE]
    rows += [{"share": "2x8", "stage": "nerf", "process": 1, "batch": 8, "error": "OutOfMemoryError('CUDA')"}]
    rows += [_row("2x8", s, 1, 8, 150.0) for s in ("dmtet", "texture")]
    stages, shares = aggregate(rows, SCHEDULE)
    assert [s["share"] for s in shares] == ["1x8"]
    assert next(r for r in stages if r["share"] == "2x8" and r["stage"] == "nerf")["error"].startswith("OutOfMemory")
    md = to_markdown({"device": "test", "date": "2026-12-03", "torch": "x", "preset": "paper", "scale": "full",
                      "warmup": 3, "seconds": 12, "command": "c", "schedule": SCHEDULE, "stages": stages,
                      "shares": shares})
    assert "| 2x8 | nerf | error: OutOfMemoryError" in md and "| 1x8 | nerf |" in md


def test_the_plan_times_every_share_at_every_stage_then_the_mix_alone_and_together() -> None:
    windows = plan(["1x8", "3x4"], ["nerf", "texture"], ["nerf:4", "texture:2"])
    assert [name for name, _ in windows] == ["1x8", "1x8", "3x4", "3x4", "nerf:4+texture:2 alone",
                                              "nerf:4+texture:2 alone", "nerf:4+texture:2 together"]
    assert windows[2][1] == [(0, "nerf", 4), (1, "nerf", 4), (2, "nerf", 4)]
    assert windows[5][1] == [(1, "texture", 2)] and windows[6][1] == [(0, "nerf", 4), (1, "texture", 2)]
    for bad in ("nerf", "bake:2", "texture:0"):
        with pytest.raises(argparse.ArgumentTypeError, match="STAGE:BATCH"):
            parse_mix(bad)


def test_mixed_stages_report_the_share_of_their_alone_rate_each_kept() -> None:
    mix = ["nerf:4", "texture:4"]
    alone = {"nerf": random.uniform(300, 500), "texture": random.uniform(400, 800)}
    slow = {"nerf": random.uniform(1.1, 2.5), "texture": random.uniform(1.1, 2.5)}
    rows = [_row("nerf:4+texture:4 alone", s, k, 4, alone[s]) for k, s in enumerate(alone)]
    rows += [_row("nerf:4+texture:4 together", s, k, 4, alone[s] * slow[s]) for k, s in enumerate(alone)]
    eff = mix_efficiency(rows, mix)
    assert eff["kept"]["0:nerf"] == pytest.approx(1 / slow["nerf"], abs=2e-3)
    assert eff["throughput_vs_one_after_another"] == pytest.approx(1 / slow["nerf"] + 1 / slow["texture"], abs=4e-3)
    assert "error" in mix_efficiency(rows[:3], mix) and mix_efficiency(rows, []) is None
