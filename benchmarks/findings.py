"""The paper's findings as verdicts on our numbers: reproduced, refuted or inconclusive.

Each finding compares two ablation rows (or two schedules) on one metric over the same scenes and
pipeline seeds. Per seed: the mean over scenes of each side, and the paired difference (b − a, scene
by scene). The verdict sets the mean paired difference against the seed spread (the larger of the
two sides' ranges over the seeds):

* a directional claim (``expect`` = +1: b better, −1: b worse) is ``reproduced`` when the mean
  difference goes the claimed way by more than the spread and every seed agrees in sign, ``refuted``
  when the same holds the other way, else ``inconclusive``;
* a flatness claim (``expect`` = 0, a sweep's rows) is ``reproduced`` when the sweep's range of means
  stays within the spread, ``refuted`` when it exceeds twice the spread, else ``inconclusive``.

"Better" is higher for PSNR-like metrics and lower for errors (``LOWER_IS_BETTER``). The records
are the ablation records of ``benchmarks/ablations.py`` (``row`` names; ``key`` names another
field, e.g. a schedule label, for records compared by something else). ``findings.json`` holds one
list of objects over every size run.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from assets_store.atomic import atomic_write_text

LOWER_IS_BETTER = frozenset({"chamfer", "colour_deviation"})
FINDING_METRICS = ("novel_psnr", "detail_psnr")


@dataclass(frozen=True)
class Finding:
    name: str
    a: tuple[str, ...]  # one row, or a sweep's rows for a flatness claim
    b: tuple[str, ...]
    expect: int  # +1: b better than a; −1: b worse; 0: flat over a + b
    paper: str


FINDINGS: tuple[Finding, ...] = (
    Finding("high-pass 2D (ours) beats Base (3D prior only)", ("base",), ("ours",), +1, "Fig. 7, 9"),
    Finding("high-pass 2D (ours) beats the full-pass 2D prior", ("full_pass_2d",), ("ours",), +1, "Fig. 7, 8"),
    Finding("the high-passed 2D prior: VSD (ours) beats SDS (no fine-tuning)", ("high_pass_2d_sds",), ("ours",), +1,
            "Fig. 9"),
    Finding("fine-tuning the 3D prior (VSD) hurts", ("ours",), ("finetuned_3d",), -1, "Fig. 11"),
    Finding("k2D: 0 is worst (k2D = 0 against 1)", ("base",), ("k2d=1",), +1, "Table 2"),
    Finding("k2D: flat over 1 … 5", ("k2d=1", "k2d=2", "ours"), ("k2d=4", "k2d=5"), 0, "Table 2"),
    Finding("r: flat over 0.2 … 0.8", ("r=0.2", "r=0.4", "ours"), ("r=0.8",), 0, "Table 3"),
)


def _better(metric: str, x: float) -> float:
    """``x`` as an improvement: positive is better for ``metric``."""
    return -x if metric in LOWER_IS_BETTER else x


def _by_seed_scene(records: Sequence[Mapping[str, Any]], key: str, name: str, metric: str) -> dict[str, float]:
    out = {}
    for r in records:
        v = r.get(metric)
        if r.get(key) == name and "error" not in r and v is not None and math.isfinite(v):
            out[r["scene"]] = float(v)
    return out


def _mean(values: Sequence[float]) -> float:
    return sum(values) / len(values)


def judge(finding: Finding, by_seed: Mapping[int, Sequence[Mapping[str, Any]]], metric: str, size: str,
          key: str = "row") -> dict[str, Any] | None:
    """One verdict row, or None when a row of the finding is missing from the records."""
    seeds = sorted(by_seed)
    names = (*finding.a, *finding.b)
    values = {(s, n): _by_seed_scene(by_seed[s], key, n, metric) for s in seeds for n in names}
    scenes = sorted(set.intersection(*(set(v) for v in values.values()))) if values else []
    if not scenes or not seeds:
        return None
    means = {(s, n): _mean([values[s, n][c] for c in scenes]) for s in seeds for n in names}
    rows_range = max(max(means[s, n] for s in seeds) - min(means[s, n] for s in seeds) for n in names)
    mean_of = {n: _mean([means[s, n] for s in seeds]) for n in names}
    a, b = _mean([mean_of[n] for n in finding.a]), _mean([mean_of[n] for n in finding.b])
    if finding.expect == 0:
        delta = max(mean_of.values()) - min(mean_of.values())
        per_seed = [max(means[s, n] for n in names) - min(means[s, n] for n in names) for s in seeds]
        verdict = ("reproduced" if delta <= rows_range else "refuted" if delta > 2 * rows_range
                   else "inconclusive")
    else:
        (na,), (nb,) = finding.a, finding.b
        per_seed = [_mean([values[s, nb][c] - values[s, na][c] for c in scenes]) for s in seeds]
        delta = _mean(per_seed)
        gain = [finding.expect * _better(metric, d) for d in per_seed]
        verdict = ("reproduced" if all(g > 0 for g in gain) and _mean(gain) > rows_range
                   else "refuted" if all(g < 0 for g in gain) and -_mean(gain) > rows_range else "inconclusive")
    return {"finding": finding.name, "metric": metric, "a": a, "b": b, "delta": delta, "spread": rows_range,
            "seeds": seeds, "size": size, "verdict": verdict, "a_rows": list(finding.a), "b_rows": list(finding.b),
            "delta_per_seed": per_seed, "scenes": scenes, "paper": finding.paper}


def judge_all(by_seed: Mapping[int, Sequence[Mapping[str, Any]]], size: str,
              findings: Sequence[Finding] = FINDINGS, metrics: Sequence[str] = FINDING_METRICS,
              key: str = "row") -> list[dict[str, Any]]:
    return [row for f in findings for m in metrics if (row := judge(f, by_seed, m, size, key)) is not None]


def merge_findings(path: Path, rows: Sequence[Mapping[str, Any]],
                   supersedes: Callable[[Mapping[str, Any]], bool] | None = None) -> list[dict[str, Any]]:
    """``path``'s list with the rows of the same (size, finding, metric), and those ``supersedes`` names (e.g.
    the same finding judged on fewer schedules), replaced by ``rows``; written atomically."""
    kept: list[dict[str, Any]] = []
    if path.is_file():
        try:
            kept = list(json.loads(path.read_text()))
        except (ValueError, TypeError) as exc:
            raise ValueError(f"{path} is not a findings list ({exc}); move it away to start a new one") from exc
    new_keys = {(r["size"], r["finding"], r["metric"]) for r in rows}
    merged = [r for r in kept if (r.get("size"), r.get("finding"), r.get("metric")) not in new_keys
              and not (supersedes is not None and supersedes(r))] + list(rows)
    atomic_write_text(path, json.dumps(merged, indent=1, allow_nan=True) + "\n")
    return merged


FINDINGS_HEAD = """\
# The paper's findings on the synthetic-scene benchmark

Written by `python -m benchmarks.quality` and `python -m benchmarks.schedule_curve`
(`benchmarks/findings.py`): each row compares two ablation rows (or two schedules) on the same
scenes and pipeline seeds. a, b: means over scenes and seeds; Δ: the mean paired difference b − a
(for a flatness claim: the sweep's range of means); spread: the larger of the rows' ranges over the
seeds. `reproduced`: the claimed direction by more than the spread, every seed agreeing (flatness:
range within the spread); `refuted`: the other way by more than the spread (flatness: over twice the
spread); otherwise `inconclusive`. Sizes and their machines, dates and commands:
`quality_ablations_<size>.md`, `schedule_curve_<gpu>.md`.

"""


def write_findings(results: Path, rows: Sequence[Mapping[str, Any]],
                   supersedes: Callable[[Mapping[str, Any]], bool] | None = None) -> list[dict[str, Any]]:
    """Merge ``rows`` into ``results/findings.json`` and rewrite ``findings.md`` from the merged list."""
    merged = merge_findings(results / "findings.json", rows, supersedes)
    atomic_write_text(results / "findings.md", FINDINGS_HEAD + findings_markdown(merged))
    return merged


def findings_markdown(rows: Sequence[Mapping[str, Any]]) -> str:
    lines = ["| size | finding (paper) | metric | a | b | Δ (b − a) | per seed | spread | scenes | verdict |",
             "|---|---|---|---:|---:|---:|---|---:|---:|---|"]
    for r in rows:
        per = ", ".join(f"{d:+.2f}" for d in r["delta_per_seed"])
        lines.append(f"| {r['size']} | {r['finding']} ({r['paper']}) | {r['metric']} | {r['a']:.2f} | {r['b']:.2f} "
                     f"| {r['delta']:+.2f} | {per} | {r['spread']:.2f} | {len(r['scenes'])} | **{r['verdict']}** |")
    return "\n".join(lines) + "\n"
