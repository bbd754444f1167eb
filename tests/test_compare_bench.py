"""``benchmarks.compare``: a benchmark run A B B A between a git revision and the working tree, joined."""

from __future__ import annotations

import json
import random
import subprocess
from pathlib import Path

import pytest

from benchmarks.compare import ORDER, CompareError, compare, main

BENCH = '''
import argparse, json, sys
from pathlib import Path
p = argparse.ArgumentParser()
p.add_argument("--fail", action="store_true")
p.add_argument("--out", type=Path)
args = p.parse_args()
if args.fail:
    sys.exit("this side cannot run")
level = float((Path(__file__).parent / "level.txt").read_text())
rows = [{"stage": s, "batch": b, "ms_per_step": level * b, "peak_gib": 1.5, "device": "cpu"}
        for s in ("nerf", "dmtet") for b in (1, 4)]
(args.out / "speed_cpu.json").write_text(json.dumps({"rows": rows}))
(args.out / "speed_cpu_extra.json").write_text(json.dumps({"note": "a file without rows is not the result"}))
'''


def _git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", "-C", str(repo), "-c", "user.email=t@example.com", "-c", "user.name=t", *args],
                          check=True, capture_output=True, text=True).stdout


@pytest.fixture
def repo(tmp_path: Path) -> tuple[Path, float, float]:
    """A repository whose benchmark reports ``level`` ms per step: ``a`` committed, ``b`` in the working tree."""
    rng = random.Random()
    a, b = rng.uniform(5, 50), rng.uniform(5, 50)
    root = tmp_path / "repo"
    (root / "fakebench").mkdir(parents=True)
    (root / "fakebench" / "__init__.py").write_text("")
    (root / "fakebench" / "speed.py").write_text(BENCH)
    (root / "fakebench" / "level.txt").write_text(f"{a}")
    _git(tmp_path, "init", "-q", str(root))
    _git(root, "add", ".")
    _git(root, "commit", "-q", "-m", "a")
    (root / "fakebench" / "level.txt").write_text(f"{b}")  # uncommitted: side B runs it
    return root, a, b


def test_both_orders_join_by_row_and_give_b_over_a(repo: tuple[Path, float, float], tmp_path: Path) -> None:
    root, a, b = repo
    out = tmp_path / "results"
    out.mkdir()
    result = compare("HEAD", "fakebench.speed", [], "fake", "cpu", out, ["stage", "batch"], root)
    assert result["order"] == list(ORDER) == ["a", "b", "b", "a"] and result["b_dirty"]
    assert result["a_commit"] == result["b_commit"] == _git(root, "rev-parse", "HEAD").strip()
    rows = {(r["stage"], r["batch"], r["field"]): r for r in result["rows"]}
    assert set(rows) == {(s, n, f) for s in ("nerf", "dmtet") for n in (1, 4) for f in ("ms_per_step", "peak_gib")}
    for stage in ("nerf", "dmtet"):
        for batch in (1, 4):
            speed = rows[stage, batch, "ms_per_step"]
            assert speed["a"] == pytest.approx([a * batch] * 2) and speed["b"] == pytest.approx([b * batch] * 2)
            assert speed["ratio_b_over_a"] == pytest.approx(b / a)
            assert rows[stage, batch, "peak_gib"]["ratio_b_over_a"] == pytest.approx(1.0)
    assert json.loads((out / "fake_compare_cpu.json").read_text())["rows"] == result["rows"]
    md = (out / "fake_compare_cpu.md").read_text()
    assert f"{b / a:.3f}" in md and "uncommitted" in md
    assert sorted(p.name for p in out.iterdir()) == ["fake_compare_cpu.json", "fake_compare_cpu.md"]
    assert len(_git(root, "worktree", "list").splitlines()) == 1  # the revision's worktree is gone


def test_a_failing_side_names_its_output_and_leaves_no_worktree(repo: tuple[Path, float, float],
                                                                tmp_path: Path) -> None:
    root, _, _ = repo
    with pytest.raises(CompareError, match=r"(?s)side a .* exited 1.*this side cannot run"):
        compare("HEAD", "fakebench.speed", ["--fail"], "fake", "cpu", tmp_path, ["stage", "batch"], root)
    assert len(_git(root, "worktree", "list").splitlines()) == 1


def test_the_command_line_refuses_a_bad_revision_and_a_missing_module(repo: tuple[Path, float, float],
                                                                       tmp_path: Path,
                                                                       capsys: pytest.CaptureFixture[str]) -> None:
    root, _, _ = repo
    out = tmp_path / "results"
    assert main(["--rev", "no-such-rev", "--name", "x", "--out", str(out), "--repo", str(root), "--",
                 "fakebench.speed"]) == 1
    assert "no-such-rev" in capsys.readouterr().err and not list(out.iterdir())
    assert main(["--rev", "HEAD", "--name", "x"]) == 2  # no "--": nothing to run
    with pytest.raises(SystemExit):
        main(["--rev", "HEAD", "--name", "x", "--"])
