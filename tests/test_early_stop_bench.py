"""``benchmarks.early_stop``: a cell that fails is reported and retried later; the others' records stay."""

from __future__ import annotations

import json
import random
from pathlib import Path

import pytest

import benchmarks.early_stop as bench
from benchmarks.early_stop import BASES, run


def test_a_failing_cell_costs_only_itself_and_is_retried(tmp_path: Path, monkeypatch, capsys) -> None:
    rng = random.Random(5)
    calls: list[str] = []

    def fake_run(scenes, schedules, device, work, eval_cfg, oracle):  # the worker's signature
        calls.append(scenes[0].name)
        if scenes[0].name == "box":
            raise RuntimeError("CUDA error: an illegal memory access")
        return [{"scene": scenes[0].name, "points": [{"stage": "bake", "novel_psnr": 20 + rng.random()}]}]

    monkeypatch.setattr(bench, "run_error_time", fake_run)
    log = tmp_path / "cells.records.jsonl"
    base = BASES["bench-cpu"]
    records, failed = run(["box", "mug"], [base], [0, 1], "cpu", tmp_path / "work", None, 1, log, (True,))
    assert sorted(r["scene"] for r in records) == ["mug", "mug"] and len(failed) == 2
    assert all(f.endswith(" box") for f in failed)
    assert "illegal memory access" in capsys.readouterr().err
    assert [json.loads(line)["scene"] for line in log.read_text().splitlines()] == ["mug", "mug"]
    calls.clear()
    records, failed = run(["box", "mug"], [base], [0, 1], "cpu", tmp_path / "work", None, 1, log, (True,))
    assert calls == ["box", "box"] and len(records) == 2 and len(failed) == 2  # only the failed cells run again


def test_cli_exits_nonzero_when_a_cell_failed(tmp_path: Path, monkeypatch) -> None:
    def broken(*args):
        raise ValueError("no surface")

    monkeypatch.setattr(bench, "run_error_time", broken)
    code = bench.main(["--schedules", "bench-cpu", "--scenes", "mug", "--seeds", "0", "--variants", "early",
                       "--work", str(tmp_path / "w"), "--results", str(tmp_path), "--name", "x"])
    assert code == 1 and not (tmp_path / "x.records.jsonl").exists()


def test_early_runs_carry_their_stop_rule_and_one_records_file_holds_one_rule(tmp_path: Path, monkeypatch) -> None:
    schedules: list[str] = []

    def fake_run(scenes, schedules_, device, work, eval_cfg, oracle):
        schedules.append(" ".join(schedules_[0].overrides))
        return [{"scene": scenes[0].name, "points": [{"stage": "bake", "novel_psnr": random.uniform(15, 25)}]}]

    monkeypatch.setattr(bench, "run_error_time", fake_run)
    log, base = tmp_path / "rule.records.jsonl", BASES["bench-cpu"]
    records, _ = run(["mug"], [base], [0], "cpu", tmp_path / "work", None, 1, log, (False, True), rule="reference")
    assert [r.get("stop_rule") for r in records] == [None, "reference"]
    assert records[1]["stop_stages"] == ["nerf", "dmtet"]
    assert "early_stop_watch_sides" not in schedules[0] and "*.loop.early_stop_watch_sides=false" in schedules[1]
    with pytest.raises(ValueError, match="another --name"):
        run(["mug"], [base], [1], "cpu", tmp_path / "work", None, 1, log, (True,), rule="sides")
    assert len(log.read_text().splitlines()) == 2  # nothing appended under the second rule
    assert bench.variant_schedule(base, 0, True).label.endswith(".early-sides.s0")
    # The reference rule in the default stages keeps the stores of the records from before the side views.
    assert bench.variant_schedule(base, 0, True, "reference").label.endswith(".early.s0")
    texture = bench.variant_schedule(base, 0, True, "sides", ("texture",))
    assert texture.label.endswith(".early-sides-texture.s0")
    assert "texture.loop.early_stop=true" in texture.overrides and "nerf.loop.early_stop=false" in texture.overrides
