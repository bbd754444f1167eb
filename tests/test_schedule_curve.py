"""``benchmarks.schedule_curve`` and ``benchmarks.bake_gap``: the summaries judge what the records say."""

from __future__ import annotations

import json
import random
from pathlib import Path

import pytest

from benchmarks import bake_gap, schedule_curve
from tests.bench_records import glb_record


def _records(rng: random.Random, gain: float, noise: float) -> list[dict]:
    """Three scenes × three schedules × three seeds: a gain per schedule, a per-seed offset of up to
    ``noise`` (the seed spread) and a small jitter per run."""
    out = []
    for scene in ("mug", "tin", "gift"):
        start, offsets = rng.uniform(18, 30), [rng.uniform(-noise, noise) for _ in range(3)]
        offsets[:2] = [-noise, noise]  # the spread is the full 2 × noise
        for i, base in enumerate(("paper/40", "paper/20", "paper/10")):
            out += [glb_record(base, scene, seed, start + i * gain + offsets[seed] + rng.uniform(-0.02, 0.02))
                    for seed in (0, 1, 2)]
    return out


def test_a_rising_curve_moves_and_a_flat_one_flattens() -> None:
    rng = random.Random(3)
    rising = schedule_curve.curve(schedule_curve.glb_rows(_records(rng, gain=1.0, noise=0.05)), "stochastic")
    flat = schedule_curve.curve(schedule_curve.glb_rows(_records(rng, gain=0.0, noise=0.3)), "stochastic")
    for points in rising.values():
        assert [p["base"] for p in points] == ["paper/40", "paper/20", "paper/10"]  # ordered by length
        verdict = schedule_curve.flattens(points)
        assert verdict["moves"] and verdict["flat_from"] == "still rising"
        assert verdict["first_to_last"] == pytest.approx(points[-1]["novel_psnr"] - points[0]["novel_psnr"])
    for points in flat.values():
        verdict = schedule_curve.flattens(points)
        assert not verdict["moves"] and verdict["flat_from"] == "paper/40"


def test_more_steps_finding_and_the_written_files(tmp_path: Path) -> None:
    rng = random.Random(8)
    records = [*_records(rng, gain=0.8, noise=0.05), glb_record("paper/10", "mug", 0, 30.0, "noise-free")]
    files = [tmp_path / "st.records.jsonl"]
    files[0].write_text("".join(json.dumps(r) + "\n" for r in records))
    assert schedule_curve.main(["--records", str(files[0]), "--results", str(tmp_path), "--name", "c"]) == 0
    findings = json.loads((tmp_path / "findings.json").read_text())
    assert {f["verdict"] for f in findings} == {"reproduced"}
    assert {f["metric"] for f in findings} == {"novel_psnr", "detail_psnr"}
    assert all(set(f) >= {"finding", "metric", "a", "b", "delta", "spread", "seeds", "size", "verdict"}
               for f in findings)
    text = (tmp_path / "c.md").read_text()
    assert "paper/10 beats paper/40" in text and "noise-free" in text and "still rising" in text


def test_bake_gap_summary_counts_runs_within_the_bound() -> None:
    rng = random.Random(11)
    records = [{"variant": v, "scene": s, "seed": seed, "gap_psnr": g, "gap_detail_psnr": rng.uniform(-1, 0),
                "bake_s": rng.uniform(5, 50), "faces": rng.randint(1000, 50000)}
               for v, gaps in (("preset", (-1.2, -0.1, 0.2)), ("2048²", (-0.2, -0.25, 0.1)))
               for s, g in zip(("box", "mug", "tin"), gaps, strict=True) for seed in (0,)]
    rows = {r["variant"]: r for r in bake_gap.summarise(records)}
    assert rows["preset"]["within_0.3"] == 2 and rows["preset"]["worst_scene"] == "box"
    assert rows["2048²"]["within_0.3"] == 3 and rows["2048²"]["gap_psnr"] == pytest.approx(-0.35 / 3)
    assert "| preset | 3 |" in bake_gap.markdown(list(rows.values()))


def test_bake_gap_refuses_unknown_variants_and_missing_records(tmp_path: Path) -> None:
    with pytest.raises(SystemExit):
        bake_gap.main(["--records", str(tmp_path / "r.jsonl"), "--variants", "8192²"])
    with pytest.raises(SystemExit):
        bake_gap.main([])
