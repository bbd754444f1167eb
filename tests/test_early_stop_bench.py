"""``benchmarks.early_stop``: a cell that fails is reported and retried later; the others' records stay."""

from __future__ import annotations

import json
import random
from pathlib import Path

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
