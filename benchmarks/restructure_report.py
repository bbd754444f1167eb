"""The stage-module restructuring measured: line counts per folder before and after, the largest file,
byte identity of one photo's outputs made by the code before and after, and a store written by the
code before read (cached, not re-run) by the code after.

    python -m benchmarks.restructure_report --before-ref 05c7323 --before-store OLD --after-store NEW \\
        --photo /tmp/photos/mug.jpg

OLD and NEW are stores of the same photo under the draft preset, made with ``morpheus3d run`` by the
code at ``--before-ref`` and by the current code (one CPU thread each: several threads make some CPU
reductions' summation order, and so the last bits of the DMTet stage, vary from run to run).
Writes ``benchmarks/results/restructure.{json,md}``.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import torch

from assets_store.atomic import atomic_write_text
from ops.config.presets import preset
from ops.engine.pipeline import run_photo
from ops.engine.stage_ids import RENAMED_STAGES, STAGE_IDS
from ops.engine.store_layout import open_store

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
FOLDERS = ("morpheus_core", "ops", "orchestration", "assets_store", "tests", "benchmarks")
TIMING = ("wall", "seconds")  # metrics that record time, not results


def _git(*args: str) -> str:
    return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, check=True).stdout


def line_counts(ref: str | None) -> dict[str, dict[str, int]]:
    """Per folder: Python files and lines at ``ref`` (None: the working tree), and the largest file."""
    files = (_git("ls-tree", "-r", "--name-only", ref) if ref else _git("ls-files")).split()
    out: dict[str, dict[str, int]] = {}
    sizes: dict[str, int] = {}
    for name in (f for f in files if f.endswith(".py")):
        text = _git("show", f"{ref}:{name}") if ref else (ROOT / name).read_text(encoding="utf-8")
        sizes[name] = len(text.splitlines())
    for folder in FOLDERS:
        mine = {k: v for k, v in sizes.items() if k.startswith(folder + "/")}
        out[folder] = {"files": len(mine), "lines": sum(mine.values())}
    outside = {k: v for k, v in sizes.items() if not k.startswith("benchmarks/")}
    largest = max(outside, key=outside.get)
    out["largest outside benchmarks/"] = {"file": largest, "lines": outside[largest]}  # type: ignore[dict-item]
    out["files over 400 lines outside benchmarks/"] = {"files": sum(v > 400 for v in outside.values()),
                                                       "lines": 0}
    return out


def _stage_dirs(photo_dir: Path) -> dict[str, Path]:
    return {RENAMED_STAGES.get(p.name, p.name): p for p in photo_dir.iterdir() if (p / "manifest.json").is_file()}


def identity(before: Path, after: Path) -> list[dict]:
    """Per stage: which output files and which metrics (timings aside) differ."""
    rows = []
    old, new = _stage_dirs(before), _stage_dirs(after)
    for stage in STAGE_IDS:
        a = json.loads((old[stage] / "manifest.json").read_text())
        b = json.loads((new[stage] / "manifest.json").read_text())
        files = sorted(set(a["outputs"]) | set(b["outputs"]))
        differ = [f for f in files if a["outputs"].get(f, {}).get("sha256") != b["outputs"].get(f, {}).get("sha256")]
        metrics = [k for k in sorted(set(a["metrics"]) | set(b["metrics"]))
                   if not any(t in k for t in TIMING) and a["metrics"].get(k) != b["metrics"].get(k)]
        rows.append({"stage": stage, "files": len(files), "files_differ": differ,
                     "metrics": len(a["metrics"]), "metrics_differ": metrics})
    return rows


def read_old_store(before_store: Path, photo: Path) -> dict[str, str]:
    """A copy of the old store opened and run by the current code: what each stage did."""
    with tempfile.TemporaryDirectory() as tmp:
        copy = Path(tmp) / "store"
        shutil.copytree(before_store, copy)
        store = open_store(copy)
        outcome = run_photo(photo, store, preset("draft"), "draft", photo.name)
        return {s.stage: s.status for s in outcome.stages}


def to_markdown(res: dict) -> str:
    lines = [f"# Stage-module restructuring: structure and identity ({res['date']})", "",
             f"Machine: {res['machine']}. Command: `{res['command']}`.", "",
             "## Python lines per folder", "", "| folder | files before | lines before | files after | lines after |",
             "|---|---|---|---|---|"]
    for folder in FOLDERS:
        b, a = res["lines_before"][folder], res["lines_after"][folder]
        lines.append(f"| {folder}/ | {b['files']} | {b['lines']} | {a['files']} | {a['lines']} |")
    for when in ("before", "after"):
        big = res[f"lines_{when}"]["largest outside benchmarks/"]
        over = res[f"lines_{when}"]["files over 400 lines outside benchmarks/"]["files"]
        lines.append(f"\nLargest file outside benchmarks/ {when}: `{big['file']}` ({big['lines']} lines); "
                     f"files over 400 lines: {over}.")
    lines += ["", f"## The bundled mug, draft preset, CPU: code at {res['before_ref']} against the current code", "",
              "| stage | output files | differing files | metrics | differing metrics (timings aside) |",
              "|---|---|---|---|---|"]
    for row in res["identity"]:
        lines.append(f"| {row['stage']} | {row['files']} | {', '.join(row['files_differ']) or 'none'} | "
                     f"{row['metrics']} | {', '.join(row['metrics_differ']) or 'none'} |")
    lines += ["", "`runlog.parquet` records each logged step's wall time, so it differs between any two runs; "
              "`qa.json` groups its checks by stage id (`nerf`, `texture`, `bake` for `nerf_fit`, "
              "`texture_refine`, `uv_bake`) and its skipped-metric messages name the modules' new paths "
              "(`morpheus_core/metrics/…`); nothing else in it differs. Both stores were made with one CPU "
              "thread (`OMP_NUM_THREADS=1`, `torch.set_num_threads(1)`): with two, the DMTet stage's last bits vary "
              "between runs of the same code (seen with the code before as well).", "",
              "## The store written by the code before, opened by the current code", "",
              " · ".join(f"{k} {v}" for k, v in res["old_store_read"].items()), ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--before-ref", required=True, help="git commit of the code before the restructuring")
    p.add_argument("--before-store", type=Path, required=True)
    p.add_argument("--after-store", type=Path, required=True)
    p.add_argument("--photo", type=Path, required=True, help="the photo both stores hold (same path as when made)")
    args = p.parse_args(argv)
    key = args.photo.name
    machine = (f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
               f"torch {torch.__version__}")
    res = {
        "date": dt.date.today().isoformat(), "machine": machine,
        "command": "python -m benchmarks.restructure_report " + " ".join(sys.argv[1:] if argv is None else argv),
        "before_ref": args.before_ref, "lines_before": line_counts(args.before_ref), "lines_after": line_counts(None),
        "identity": identity(args.before_store / key, args.after_store / key),
        "old_store_read": read_old_store(args.before_store, args.photo),
    }
    RESULTS.mkdir(parents=True, exist_ok=True)
    atomic_write_text(RESULTS / "restructure.json", json.dumps(res, indent=2) + "\n")
    atomic_write_text(RESULTS / "restructure.md", to_markdown(res))
    print(to_markdown(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
