"""``benchmarks.speed_ab``: one call's tables per pair, ratios per pair, geometric mean over both orders."""

from __future__ import annotations

import json
import random
from pathlib import Path

import pytest

from benchmarks.speed_ab import compare, main


def table(ms: dict[tuple[str, int], float]) -> dict:
    return {"device": "test GPU", "torch": "2.13.0", "date": "2026-12-03",
            "rows": [{"stage": s, "batch": b, "ms_per_step": v * b} for (s, b), v in ms.items()]}


def test_a_pair_in_each_order_cancels_a_constant_order_effect() -> None:
    rng = random.Random(7)
    true_ref = {("texture", 8): 100 + rng.random(), ("nerf", 1): 70 + rng.random(), ("dmtet", 4): 50.0}
    second = 1 / 1.2  # whatever runs second in a call reads 20 % faster; the change is truly 10 % faster
    ref_first = (table(true_ref), table({k: 0.9 * v * second for k, v in true_ref.items()}), "ref")
    new_first = (table({k: v * second for k, v in true_ref.items()}), table({k: 0.9 * v for k, v in true_ref.items()}),
                 "new")
    new_first[0]["rows"].append({"stage": "texture", "batch": 16, "ms_per_step": 1.0})  # not in every table
    rows = compare([ref_first, new_first])
    assert [(r["stage"], r["batch"]) for r in rows] == [("nerf", 1), ("dmtet", 4), ("texture", 8)]
    for r in rows:
        assert [c["ratio"] for c in r["pairs"]] == pytest.approx([0.75, 1.08])  # each call alone misleads
        assert r["ratio"] == pytest.approx(0.9, abs=1e-3) and r["orders"] == ["new", "ref"]


def test_cli_writes_both_files_and_refuses_a_bad_order(tmp_path: Path) -> None:
    paths = []
    for name, ms in (("r", 80.0), ("n", 60.0)):
        paths.append(tmp_path / f"{name}.json")
        paths[-1].write_text(json.dumps(table({("dmtet", 1): ms})))
    assert main(["--pair", str(paths[0]), str(paths[1]), "ref", "--name", "ab", "--results", str(tmp_path)]) == 0
    assert "| dmtet | 1 | 80.0 → 60.0 (-25%) | 0.750 | -25% |" in (tmp_path / "ab.md").read_text()
    assert json.loads((tmp_path / "ab.json").read_text())["rows"][0]["ratio"] == 0.75
    with pytest.raises(SystemExit):
        main(["--pair", str(paths[0]), str(paths[1]), "second", "--name", "x", "--results", str(tmp_path)])
