"""`make demo` runs benchmarks/frequency_demo.py: check it end to end at a tiny size."""

from __future__ import annotations

import json
from pathlib import Path

from benchmarks.frequency_demo import DemoConfig, main, run_demo

ROOT = Path(__file__).resolve().parent.parent
PHOTOS = sorted((ROOT / "examples" / "photos").glob("*.jpg"))


def test_bundled_examples_exist() -> None:
    assert {p.stem for p in PHOTOS} >= {"mug", "bottle", "box"}


def test_high_pass_row_beats_base_and_full_pass(tmp_path: Path) -> None:
    res = run_demo(PHOTOS[0], DemoConfig(size=48, steps=120))
    rows = {r["row"]: r for r in res["rows"]}
    assert res["c_beats_a_and_b"]
    # The full-pass 2D prior imports its colour cast; the high-pass one does not.
    assert rows["b_full_pass_2d"]["mean_colour_error_de76"] > 3 * rows["c_high_pass_2d"]["mean_colour_error_de76"]
    # Base lacks the detail the 2D prior brings back.
    assert rows["c_high_pass_2d"]["hf_energy_ratio"] > rows["a_base"]["hf_energy_ratio"]


def test_demo_command_writes_figures_and_tables(tmp_path: Path) -> None:
    out, results = tmp_path / "demo", tmp_path / "results"
    code = main(["--image", str(PHOTOS[0]), "--size", "32", "--steps", "60", "--out", str(out),
                 "--results", str(results)])
    assert code == 0
    stem = PHOTOS[0].stem
    for f in [out / f"{stem}_rows.png", out / f"{stem}_psd.png", results / "frequency_demo.md"]:
        assert f.is_file() and f.stat().st_size > 0
    summary = json.loads((results / "frequency_demo.json").read_text())
    assert summary["results"][0]["c_beats_a_and_b"] is True
    assert not list(out.glob(".*.tmp"))  # atomic writes leave no temporaries
