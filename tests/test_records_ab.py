"""``benchmarks.records_ab``: two record files paired by cell, the differences and the seed-range rule."""

from __future__ import annotations

import json
import random
from pathlib import Path

import pytest

from benchmarks.records_ab import compare, main


def record(scene: str, seed: int, psnr: float, chamfer: float = 0.02, early: bool = True) -> dict:
    stages = [{"stage": s, "wall_s": 10.0 * i, "novel_psnr": psnr - 4 + i, "chamfer": chamfer, "fscore": 0.9}
              for i, s in enumerate(("nerf", "dmtet", "texture", "bake"), 1)]
    return {"base": "bench-cpu", "scene": scene, "seed": seed, "early_stop": early, "points": stages,
            "machine": "test", "date": "2026-12-03"}


def test_pairs_cells_and_judges_the_seed_range() -> None:
    rng = random.Random(3)
    a = [record(sc, s, 20 + rng.uniform(-1, 1)) for sc in ("mug", "box") for s in range(3)]
    shift = {"mug": 0.05, "box": 5.0}  # mug: inside its seed range; box: far outside
    b = [record(r["scene"], r["seed"], r["points"][-1]["novel_psnr"] + shift[r["scene"]]) for r in a]
    b.append(record("vase", 0, 30.0))  # no partner in A: left out
    b.append({**record("mug", 0, 0.0, early=False), "points": []} | {"error": "killed"})  # unfinished
    rows = {r["scene"]: r for r in compare(a, b)}
    assert set(rows) == {"mug", "box", "all scenes"}
    assert rows["mug"]["pairs"] == 3 and rows["all scenes"]["pairs"] == 6
    assert rows["mug"]["delta_psnr"] == pytest.approx(0.05) and rows["box"]["delta_psnr"] == pytest.approx(5.0)
    assert rows["mug"]["novel_psnr_within_spread"] and not rows["box"]["novel_psnr_within_spread"]
    assert rows["box"]["chamfer_within_spread"]  # equal Chamfer: inside its (degenerate) range
    assert rows["all scenes"]["delta_nerf_psnr"] == pytest.approx(2.525)


def test_cli_writes_results_and_refuses_disjoint_files(tmp_path: Path) -> None:
    files = []
    for name, recs in (("a", [record("mug", 0, 20.0), record("mug", 1, 21.0)]),
                       ("b", [record("mug", 0, 20.5), record("mug", 1, 21.5)]), ("c", [record("box", 0, 20.0)])):
        path = tmp_path / f"{name}.records.jsonl"
        path.write_text("".join(json.dumps(r) + "\n" for r in recs))
        files.append(path)
    assert main([str(files[0]), str(files[1]), "--name", "ab", "--results", str(tmp_path)]) == 0
    text = (tmp_path / "ab.md").read_text()
    assert "+0.50 ± 0.00 (n=2)" in text and json.loads((tmp_path / "ab.json").read_text())["rows"][0]["pairs"] == 2
    with pytest.raises(SystemExit, match=r"no .* cell finished in both"):
        main([str(files[0]), str(files[2]), "--name", "ac", "--results", str(tmp_path)])
