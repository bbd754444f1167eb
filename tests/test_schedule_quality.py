"""``benchmarks.schedule_quality``: fast against paper, scene by scene, judged against the seed spread."""

from __future__ import annotations

import json
import random
from pathlib import Path

from benchmarks import schedule_quality
from benchmarks.schedule_curve import glb_rows
from tests.bench_records import glb_record
from tests.seeds import fresh_seed


def _records(rng: random.Random, loss: dict[str, float], noise: float) -> list[dict]:
    """paper/20 and fast/20 on four scenes × three seeds; fast loses ``loss[scene]`` dB."""
    out = []
    for scene, lost in loss.items():
        start = rng.uniform(18, 30)
        offsets = [-noise, noise, rng.uniform(-noise, noise)]  # the seed spread is 2 × noise
        for seed in (0, 1, 2):
            out.append(glb_record("paper/20", scene, seed, start + offsets[seed]))
            out.append(glb_record("fast/20", scene, seed, start + offsets[seed] - lost + rng.uniform(-0.01, 0.01)))
    return out


def test_a_scene_that_loses_more_than_the_spread_is_outside_it() -> None:
    rng = random.Random(fresh_seed())
    loss = {"mug": 0.0, "tin": 0.1, "box": 1.5, "gift": -0.4}
    table = schedule_quality.compare(glb_rows(_records(rng, loss, noise=0.2)), "paper/20", "fast/20")
    by = {r["scene"]: r["novel_psnr"] for r in table}
    assert {s: by[s]["within"] for s in loss} == {"mug": True, "tin": True, "box": False, "gift": True}
    for scene, lost in loss.items():
        assert abs(by[scene]["delta"] + lost) < 0.02
        assert abs(by[scene]["spread"] - 0.4) < 0.03
        assert len(by[scene]["per_seed"]) == 3


def test_the_files_and_the_finding(tmp_path: Path) -> None:
    rng = random.Random(fresh_seed())
    records = _records(rng, {"mug": 0.0, "tin": 0.05, "box": -0.05, "gift": 0.0}, noise=0.3)
    log = tmp_path / "q.records.jsonl"
    log.write_text("".join(json.dumps(r) + "\n" for r in records))
    speed = tmp_path / "speed.json"
    speed.write_text(json.dumps({"preset": "fast", "device": "GPU", "date": "2026-12-07", "projections": [
        {"batch": 1, "min_per_object": 6.5, "nerf_min": 3.0, "dmtet_min": 1.0, "texture_min": 2.5}]}))
    assert schedule_quality.main(["--records", str(log), "--speed", str(speed), "--results", str(tmp_path),
                                  "--name", "sq"]) == 0
    result = json.loads((tmp_path / "sq.json").read_text())
    assert len(result["rows"]) == 4 and result["speed"][0]["min_per_object"] == 6.5
    text = (tmp_path / "sq.md").read_text()
    assert "within the seed spread on **4 of 4** scenes" in text
    findings = json.loads((tmp_path / "findings.json").read_text())
    assert {f["verdict"] for f in findings} == {"reproduced"}  # flat within the spread


def test_no_shared_cells_is_an_error(tmp_path: Path) -> None:
    log = tmp_path / "q.records.jsonl"
    log.write_text(json.dumps(glb_record("paper/20", "mug", 0, 25.0)) + "\n")
    assert schedule_quality.main(["--records", str(log), "--results", str(tmp_path)]) == 1
    assert not (tmp_path / "schedule_quality.json").exists()


def test_a_directional_claim_on_the_seeds_both_schedules_ran(tmp_path: Path) -> None:
    rng = random.Random(fresh_seed())
    records = _records(rng, {"mug": -1.5, "tin": -1.2, "box": -1.8, "gift": -1.4}, noise=0.2)  # fast/20 gains
    records = [r for r in records if not (r["base"] == "paper/20" and r["seed"] == 2)]  # the longer one: 2 seeds
    log = tmp_path / "q.records.jsonl"
    log.write_text("".join(json.dumps(r) + "\n" for r in records))
    assert schedule_quality.main(["--records", str(log), "--results", str(tmp_path), "--expect", "1",
                                  "--source", "test", "--name", "sq"]) == 0
    findings = json.loads((tmp_path / "findings.json").read_text())
    assert {f["finding"] for f in findings} == {"fast/20 beats paper/20"}
    assert {f["verdict"] for f in findings if f["metric"] == "novel_psnr"} == {"reproduced"}
    assert all(f["seeds"] == [0, 1] for f in findings)
