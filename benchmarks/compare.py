"""A/B of a benchmark between this tree and a git revision, in one call, in both orders.

    python -m benchmarks.compare --rev HEAD~1 --name hashgrid --tag h100 -- \\
        benchmarks.paper_speed --device cuda --mode after --batches 1 8 --tag h100

The benchmark module runs four times, A B B A (A: the tree at ``--rev``, checked out as a temporary
git worktree; B: this working tree, uncommitted changes included), so drift of the machine over the
call (clocks, other tenants, a warming GPU) falls on both sides alike. Each run writes into its own
folder (``--out <folder>`` is appended to the benchmark's arguments); its JSON result's ``rows`` are
joined on ``--keys`` (default ``stage batch``), and every numeric field of a row is compared: both
sides' values, their means and the ratio B / A. Results: ``<name>_compare_<tag>.json`` and ``.md``
in ``--out``, written after every run, so a call cut short keeps what it measured.

Ratios are only meaningful from one call on one machine; the result names the machine, the date,
both commits and the command.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from statistics import mean
from typing import Any

from assets_store.atomic import atomic_write_text

ROOT = Path(__file__).resolve().parent.parent
ORDER = ("a", "b", "b", "a")


class CompareError(RuntimeError):
    """The revision cannot be checked out, or a run did not leave one JSON result with ``rows``."""


@dataclass(frozen=True)
class Side:
    name: str  # "a" (the revision) or "b" (this tree)
    tree: Path
    commit: str


def _git(repo: Path, *args: str) -> str:
    done = subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True)
    if done.returncode != 0:
        raise CompareError(f"git {' '.join(args)} in {repo}: {done.stderr.strip()}")
    return done.stdout.strip()


def run_once(side: Side, module: str, args: Sequence[str], out: Path, log: Path) -> list[dict[str, Any]]:
    """One run of ``python -m module args --out out`` inside ``side.tree``; the rows of its JSON result."""
    out.mkdir(parents=True)  # a fresh folder per run: its one JSON result is this run's
    env = {**os.environ, "PYTHONPATH": str(side.tree)}  # the tree's packages, not the installed ones
    with log.open("w") as fh:
        code = subprocess.run([sys.executable, "-m", module, *args, "--out", str(out)], cwd=side.tree, env=env,
                              stdout=fh, stderr=subprocess.STDOUT).returncode
    if code != 0:
        tail = "\n".join(log.read_text(errors="replace").splitlines()[-20:])
        raise CompareError(f"side {side.name} ({side.commit[:10]}) exited {code}; the end of its output:\n{tail}")
    results = [p for p in sorted(out.glob("*.json")) if "rows" in json.loads(p.read_text())]
    if len(results) != 1:
        raise CompareError(f"side {side.name}: expected one JSON result with 'rows' in {out}, found "
                           f"{[p.name for p in results]}")
    return list(json.loads(results[0].read_text())["rows"])


def join(runs: Sequence[tuple[str, list[dict[str, Any]]]], keys: Sequence[str]) -> list[dict[str, Any]]:
    """Per row key and numeric field: each side's values in run order, their means and B / A."""
    values: dict[tuple[Any, ...], dict[str, dict[str, list[float]]]] = {}
    for side, rows in runs:
        for row in rows:
            key = tuple(row.get(k) for k in keys)
            for field, value in row.items():
                if field in keys or isinstance(value, bool) or not isinstance(value, (int, float)):
                    continue
                values.setdefault(key, {}).setdefault(field, {"a": [], "b": []})[side].append(float(value))
    out = []
    for key, fields in values.items():
        for field, by_side in fields.items():
            a, b = by_side["a"], by_side["b"]
            mean_a, mean_b = (mean(a) if a else None), (mean(b) if b else None)
            ratio = mean_b / mean_a if mean_a and mean_b is not None else None
            out.append({**dict(zip(keys, key, strict=True)), "field": field, "a": a, "b": b, "mean_a": mean_a,
                        "mean_b": mean_b, "ratio_b_over_a": ratio})
    return out


def to_markdown(result: dict[str, Any]) -> str:
    keys = result["keys"]
    lines = [f"# {result['name']}: A/B in both orders ({', '.join(result['order'])})", "",
             f"- A: `{result['a_commit']}` (`--rev {result['rev']}`); B: this tree at `{result['b_commit']}`"
             f"{' with uncommitted changes' if result['b_dirty'] else ''}",
             f"- machine: {result['machine']}; date: {result['date']}",
             f"- command: `{result['command']}`", "",
             "| " + " | ".join([*keys, "field", "A runs", "B runs", "B / A"]) + " |",
             "|" + "---|" * (len(keys) + 4)]
    for row in result["rows"]:
        ratio = row["ratio_b_over_a"]
        cells = [*(str(row[k]) for k in keys), row["field"], ", ".join(f"{v:.4g}" for v in row["a"]),
                 ", ".join(f"{v:.4g}" for v in row["b"]), "-" if ratio is None else f"{ratio:.3f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def compare(rev: str, module: str, args: Sequence[str], name: str, tag: str, out: Path, keys: Sequence[str],
            repo: Path = ROOT, command: str = "") -> dict[str, Any]:
    """Run ``module`` A B B A (A: ``rev`` of ``repo``, B: ``repo``'s working tree) and write the joined result."""
    b_commit = _git(repo, "rev-parse", "HEAD")
    a_commit = _git(repo, "rev-parse", "--verify", f"{rev}^{{commit}}")
    dirty = bool(_git(repo, "status", "--porcelain", "--untracked-files=no"))
    stem = out / f"{name}_compare_{tag}"
    with tempfile.TemporaryDirectory(prefix="compare_") as tmp:
        work = Path(tmp)
        _git(repo, "worktree", "add", "--detach", str(work / "a"), a_commit)
        try:
            sides = {"a": Side("a", work / "a", a_commit), "b": Side("b", repo, b_commit)}
            runs: list[tuple[str, list[dict[str, Any]]]] = []
            result: dict[str, Any] = {}
            for i, side in enumerate(ORDER):
                print(f"[{i + 1}/{len(ORDER)}] side {side} ({sides[side].commit[:10]})", flush=True)
                run_dir = work / f"run{i}_{side}"
                runs.append((side, run_once(sides[side], module, args, run_dir / "out", work / f"run{i}_{side}.log")))
                result = {"name": name, "rev": rev, "a_commit": a_commit, "b_commit": b_commit, "b_dirty": dirty,
                          "order": list(ORDER[: i + 1]), "keys": list(keys), "module": module, "args": list(args),
                          "machine": f"{platform.node()} {platform.machine()} ({os.cpu_count()} CPUs)",
                          "date": datetime.now(timezone.utc).isoformat(timespec="seconds"), "command": command,
                          "rows": join(runs, keys)}
                atomic_write_text(stem.with_suffix(".json"), json.dumps(result, indent=2) + "\n")
                atomic_write_text(stem.with_suffix(".md"), to_markdown(result))
        finally:
            _git(repo, "worktree", "remove", "--force", str(work / "a"))
    return result


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if "--" not in argv:
        print("usage: python -m benchmarks.compare --rev REV --name NAME [--tag TAG] -- MODULE [ARGS...]",
              file=sys.stderr)
        return 2
    cut = argv.index("--")
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rev", required=True, help="the revision to compare this tree against (A)")
    p.add_argument("--name", required=True, help="result name: <name>_compare_<tag>.{json,md}")
    p.add_argument("--tag", default="cpu", help="the device, as the GPU the machine reports (h100, h200) or cpu")
    p.add_argument("--keys", nargs="+", default=["stage", "batch"], help="row fields that identify a row")
    p.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    p.add_argument("--repo", type=Path, default=ROOT, help=argparse.SUPPRESS)
    args = p.parse_args(argv[:cut])
    bench = argv[cut + 1:]
    if not bench:
        p.error("name the benchmark module after --, e.g. benchmarks.paper_speed")
    args.out.mkdir(parents=True, exist_ok=True)
    try:
        compare(args.rev, bench[0], bench[1:], args.name, args.tag, args.out, args.keys, args.repo,
                "python -m benchmarks.compare " + " ".join(argv))
    except CompareError as exc:
        print(f"compare: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
